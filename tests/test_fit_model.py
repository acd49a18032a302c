"""The RAW fit's model (difstar._fit_model): configurations on one grid, mapped over,
against ``difstar.simulate`` called capture by capture and central differences; the
campaign's shared grid against each configuration's own."""

from __future__ import annotations

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from test_fit import CC, F, _data, _model

import difstar


def test_configurations_on_one_grid_are_one_map_with_the_chains_values_and_slopes():
    """Two configurations (in focus, and 1 mm defocused) on one grid with two captures
    each are mapped over (:func:`difstar._fit.jointly`): each capture's prediction is
    ``difstar.simulate``'s own, called for that capture alone, and the Jacobian's
    columns (each configuration linearised inside the map) equal central finite
    differences of the residuals."""
    params = dict(_model().params)
    params.pop("defocus/c")
    offset = params.pop("source_offset/c")
    params |= {"defocus/near": F.Param(0.0), "source_offset/near": offset,
               "defocus/far": F.Param(1e-3, True, (0.5e-3, 2e-3)),
               "source_offset/far": F.Param(np.array([-0.2, 0.4]))}
    grid = difstar.Grid(n=96, crop=(64, 64), use_defocus=True, raw_only=True)
    cfgs = (F.ConfigSpec("near", 1.0, 1.0, grid), F.ConfigSpec("far", 1.0, 1.0, grid))
    caps = tuple(F.CaptureSpec(n, c, t, (0.0, 0.0))
                 for n, c, t in (("a", "near", 0.1), ("b", "near", 1.0),
                                 ("c", "far", 0.2), ("d", "far", 2.0)))
    model = F.FitModel(CC, cfgs, caps, params)
    assert F.jointly(model)
    assert not F.jointly(F.FitModel(CC, cfgs, caps[:3], params))  # 2 and 1 captures
    u = F.to_unconstrained(model)
    x = F.from_unconstrained(model, u)
    fitter, data = _data(model, noise_sigma=1e-3)
    pred = fitter.predict(u)
    for k, cfg in enumerate(cfgs):
        camera, scene, ts, pos = F.camera_scene(model, x, cfg.name)
        for j, t in enumerate(np.asarray(ts)):
            one = eqx.tree_at(lambda s: (s.exposure_time, s.sources[0].position), scene,
                              (jnp.asarray(t), pos[j]))
            want = np.asarray(difstar.simulate(camera, one, grid).cfa)
            # to rounding: the fit's prediction is compiled with the solver's XLA
            # options (difstar._xla), which order some sums otherwise
            np.testing.assert_allclose(np.asarray(pred[cfg.name][j]), want, rtol=1e-11,
                                       atol=1e-15, err_msg=f"{cfg.name} capture {j}")
    args = F.make_args(model, data)
    jac = np.asarray(fitter._jac(u, args))
    assert jac.shape == (4 * 64 * 64, model.n_free)
    for i in range(model.n_free):
        e = np.zeros(u.shape)
        e[i] = 1e-4
        fd = (fitter.residuals(u + e, args) - fitter.residuals(u - e, args)) / 2e-4
        assert np.abs(jac[:, i]).max() > 1e-3, i
        np.testing.assert_allclose(jac[:, i], fd, atol=2e-4 * np.abs(jac[:, i]).max(),
                                   err_msg=f"column {i}")


def test_the_campaigns_configurations_share_a_grid_holding_what_each_needs():
    """The synthetic campaign's two configurations (in focus; 4.8 mm defocused) are
    planned on one grid for the fit: at least each one's own period, pupil window,
    sub-cells, nodes and sources' window; its pupil window holds each one's pupil at
    the shortest wavelength (the sampling rule's count); and each configuration's captures through
    it agree with those through its own grid to the engine's accuracy (1e-3)."""
    import dataclasses

    from difstar._fit_run import build_model, prepare
    from difstar._sampling_rules import pupil_window_for
    from difstar.io._manifest import load_manifest

    campaign = Path(__file__).resolve().parents[1] / "fit" / "synthetic-paper-camera"
    man = load_manifest(campaign / "manifest.json")
    model, caps = prepare(man)
    own = build_model(man, crops={c.configuration: caps[c.name]["crop"] for c in man.captures},
                      base_offsets={k: v["base_offset"] for k, v in caps.items()},
                      exposure_times={k: v["exposure_time"] for k, v in caps.items()},
                      pattern="RGGB")
    assert F.jointly(model) and not F.jointly(own)
    shared = model.configs[0].grid
    x = F.from_unconstrained(model, F.to_unconstrained(model))
    for cfg in own.configs:
        g, p, q = cfg.grid, cfg.grid.psf_plan, shared.psf_plan
        assert shared.n >= g.n and shared.source_window >= g.source_window
        assert q.pupil_window >= p.pupil_window and q.subcells >= p.subcells
        assert q.nodes >= p.nodes and q.use_defocus
        one = dataclasses.replace(own, configs=(cfg,),
                                  captures=own.captures_of(cfg.name))
        camera, scene, ts, pos = F.camera_scene(one, x, cfg.name)
        scene = eqx.tree_at(lambda s: (s.exposure_time, s.sources[0].position), scene,
                            (ts[-1], pos[-1]))
        geo = difstar.geometry_of(camera, scene)
        assert pupil_window_for(float(camera.lens.pupil.max_radius()), 450e-9,
                                float(geo.z_exit_pupil), CC.pixel_pitch,
                                shared.n) <= q.pupil_window
        # compiled with the inputs closed over, as concrete values (the plans' checks)
        a, b = (np.asarray(jax.jit(lambda grid=grid: difstar.simulate(
            camera, scene, grid).zeta)()) for grid in (g, shared))
        assert np.abs(b - a).max() <= 1e-3 * np.abs(a).max(), cfg.name
