"""A fit's procedure as types: :class:`Solve`, :class:`Hop`, :class:`Repeat` and
:class:`Restart`.

A stage may be given as one of these or as a dict, as a manifest writes it
(``{"free": ["rotation"], "half": 20}``, ``{"hop": {...}}``, ``{"repeat": {...}}``).
:func:`difstar.fitting.fit` checks every stage before anything solves
(:func:`._stages._check_fit_inputs`, on the dict form, so both forms get the same
checks and the same messages), then parses each into one of these types, once
(:func:`parse_stage`); the procedure reads only the types. One loop runs them for
both fitters (:func:`difstar.fitting._loop.run_procedure`): the RAW fit
(:mod:`difstar._fit_procedure`) runs :class:`Solve` (its ``free``, ``fix``,
``max_steps`` and ``sigma``), :class:`Hop`, :class:`Repeat` and :class:`Restart`; an
image fit refuses ``sigma`` and restarts, a RAW fit the image fit's windows, spikes and
noise estimates, each naming the stage."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any


def _tuple(x) -> tuple:
    return tuple(x) if isinstance(x, (list, tuple)) else (x,)


@dataclasses.dataclass(frozen=True)
class Solve:
    """One Levenberg–Marquardt solve (see :func:`difstar.fitting.fit` for each field):
    ``free`` ("all" or names) less ``fix``; ``set`` values put first; the window
    (``half``, ``annulus``); ``spikes`` (fit the spikes' pixels or profiles);
    ``noise_from_residuals`` and ``reject`` before solving; ``scan`` a parameter first;
    the solver's ``max_steps`` and ``rtol`` (None: the fit's); ``sigma`` (RAW fits):
    "prediction" takes σ from the model's prediction at the values reached, "data" or
    None from the observed values."""

    free: str | Sequence[str] = "all"
    fix: str | Sequence[str] = ()
    set: Mapping[str, Any] | None = None
    half: int | float | None = None
    annulus: Sequence[Any] | None = None
    spikes: Mapping[str, Any] | None = None
    noise_from_residuals: Mapping[str, Any] | None = None
    reject: Mapping[str, Any] | None = None
    scan: Mapping[str, Any] | None = None
    max_steps: int | float | None = None
    rtol: float | int | None = None
    sigma: str | None = None

    def __post_init__(self):
        if self.free != "all":
            object.__setattr__(self, "free", _tuple(self.free))
        object.__setattr__(self, "fix", _tuple(self.fix) if self.fix else ())
        if self.annulus is not None:
            object.__setattr__(self, "annulus", tuple(self.annulus))

    def as_dict(self) -> dict:
        """The stage as a manifest writes it: the fields that differ from the defaults
        (``free`` always)."""
        out: dict[str, Any] = {"free": self.free if self.free == "all" else list(self.free)}
        for f in dataclasses.fields(self)[1:]:
            v = getattr(self, f.name)
            if v is not None and v != ():
                out[f.name] = list(v) if isinstance(v, tuple) else v
        return out

    def without_estimates(self) -> Solve:
        """The same solve without its noise estimate and rejection (a hop's or a repeat's
        re-run compares on one yardstick: σ and the pixels as they are)."""
        return dataclasses.replace(self, noise_from_residuals=None, reject=None)


@dataclasses.dataclass(frozen=True)
class Hop:
    """Re-run the ``stages`` solving stages before it from values changed in each way
    named, keeping the lowest χ² on all pixels: ``name`` moved by each of ``offsets``;
    or each entry of ``flip`` (a name, or a tuple of names negated together) negated; or
    the values of ``set`` put, all at once."""

    name: str | None = None
    offsets: Sequence[Any] = ()
    flip: Sequence[Any] = ()
    set: Mapping[str, Any] | None = None
    stages: int | float = 2

    def __post_init__(self):
        object.__setattr__(self, "offsets", tuple(float(x) for x in self.offsets))
        object.__setattr__(self, "flip", tuple(
            q if isinstance(q, str) else tuple(q) for q in self.flip))

    def as_dict(self) -> dict:
        h: dict[str, Any] = {}
        if self.name is not None:
            h |= {"name": self.name, "offsets": list(self.offsets)}
        if self.flip:
            h["flip"] = [q if isinstance(q, str) else list(q) for q in self.flip]
        if self.set is not None:
            h["set"] = dict(self.set)
        return {"hop": h | {"stages": self.stages}}


@dataclasses.dataclass(frozen=True)
class Repeat:
    """Re-run the ``stages`` solving stages before it, round after round, until every
    parameter of ``until`` (name → tolerance) moves by less than its tolerance over a
    round, or ``max_rounds``."""

    until: Mapping[str, Any]
    stages: int | float = 2
    max_rounds: int | float = 6

    def as_dict(self) -> dict:
        return {"repeat": {"until": dict(self.until), "stages": self.stages,
                           "max_rounds": self.max_rounds}}


@dataclasses.dataclass(frozen=True)
class Restart:
    """(RAW fits) Move each channel's response-curve ``parameter`` (``phi0``, ``toe`` or
    ``knee``) by each of ``factors`` from where the solves before left it, re-solve, and
    keep what ends at a lower loss: a way out of a shallow basin of a weakly constrained
    shoulder (:func:`difstar._fit_procedure.restart_response_curves`)."""

    parameter: str = "knee"
    factors: Sequence[Any] = (0.5, 2.0)

    def __post_init__(self):
        object.__setattr__(self, "factors", tuple(self.factors))

    def as_dict(self) -> dict:
        return {"restart": {"parameter": self.parameter, "factors": list(self.factors)}}


Stage = Solve | Hop | Repeat | Restart
STAGE_TYPES = (Solve, Hop, Repeat, Restart)


def stage_dicts(stages: Sequence) -> list:
    """Each stage in the dict form the checks read (a typed stage by its
    :meth:`as_dict`, anything else as given: the checks refuse what is not a stage)."""
    return [st.as_dict() if isinstance(st, STAGE_TYPES) else st for st in stages]


def parse_stage(st: Mapping) -> Stage:
    """A checked stage's dict form as its type (a restart's unknown keys raise
    TypeError)."""
    if st.get("restart") is not None:
        return Restart(**st["restart"])
    if st.get("hop") is not None:
        h = st["hop"]
        return Hop(name=h.get("name"), offsets=tuple(h.get("offsets", ())),
                   flip=tuple(h.get("flip", ())), set=h.get("set"),
                   stages=int(h.get("stages", 2)))
    if st.get("repeat") is not None:
        r = st["repeat"]
        return Repeat(until=dict(r["until"]), stages=int(r.get("stages", 2)),
                      max_rounds=int(r.get("max_rounds", 6)))
    names = {f.name for f in dataclasses.fields(Solve)}
    return Solve(**{k: v for k, v in st.items() if k in names and v is not None})
