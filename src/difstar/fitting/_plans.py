"""How an image fit chooses its PSF plans: the margin and headroom over the Zernike
terms a stage plans for, the wavefront a plan is made for (the terms and the widest
tilt a star's shift allows), and when a plan made before serves (:func:`as_fine`).
:meth:`ImageModel.plan <difstar.fitting.ImageModel.plan>` applies them."""

from __future__ import annotations

from typing import Any

import equinox as eqx

from .._zernike import Zernike


class Shifted(eqx.Module):
    """A wavefront tilt (tx, ty) plus Zernike terms: OPD = tx x + ty y + Σ c_j Z_j."""

    zernike: Zernike | None
    tx: Any
    ty: Any

    def opd(self, x, y):
        w = self.tx * x + self.ty * y
        return w if self.zernike is None else w + self.zernike.opd(x, y)


#: The Zernike terms' margin in a fit's PSF plan: a stage plans for 1.5 × its start's
#: values, and solves again from its answer where that needs a finer plan.
PLAN_MARGIN = 1.5
#: A free Zernike term is planned for at least this fraction of its bounds' reach: a
#: solve moves it away from a start at zero, and a plan made for zero then needs a
#: second plan, program and solve (the Spitzer fit's last stage: one more compile).
PLAN_HEADROOM = 0.1


def as_fine(plan, need) -> bool:
    """Whether ``plan`` serves where ``need`` is asked for: the same method, nodes,
    period and pupil window, and no fewer sub-cells of the pupil."""
    same = (plan.method, plan.nodes, plan.period, plan.pupil_window, plan.use_defocus) \
        == (need.method, need.nodes, need.period, need.pupil_window, need.use_defocus)
    return same and plan.subcells >= need.subcells
