"""What mirrored.py and shifted.py share: write a changed copy of a manifest's FITS file
into a new folder, fit it with the same manifest (only the file swapped) and compare."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np


def write_changed_fits(src: Path, dst: Path, change) -> None:
    """Writes ``dst``: the image HDU of ``src`` that the fitter reads (``read_image``'s
    ``hdu``), as ``change(data, header)`` returns it (a new array and astropy header)."""
    from astropy.io import fits

    from difstar.io import read_image

    index = read_image(src).hdu
    with fits.open(src) as hdul:
        data, head = change(np.array(hdul[index].data), hdul[index].header.copy())
    fits.PrimaryHDU(data, head).writeto(dst)


def fit_copy(manifest: Path, out: Path, name: str, change, description: str):
    """Makes the new folder ``out`` (refused if it exists), writes ``out/name`` (the
    manifest's FITS file changed by ``change(data, header) -> (data, header)``: see
    ``write_changed_fits``), ``out/manifest.json`` (the manifest with that file) and runs
    ``difstar fit-image`` into ``out/fit``. Returns that fit's ``result.json`` as a dict,
    or None (with a message) when ``out`` exists or the manifest has more than one
    capture. On any failure removes ``out`` again (only what it made)."""
    from difstar.fitting import resolve_data_path, run_fit_image

    man = json.loads(manifest.read_text())
    if not isinstance(man["data"], dict):
        print(f"{Path(sys.argv[0]).name} takes a manifest with one capture.", file=sys.stderr)
        return None
    try:
        out.mkdir(parents=True)
    except FileExistsError:
        print(f"{out} exists: give a new folder.", file=sys.stderr)
        return None
    try:
        write_changed_fits(Path(resolve_data_path(man["data"]["path"], manifest.parent)),
                           out / name, change)
        man["data"] = dict(man["data"], path=name)
        man["description"] = description + " " + man.get("description", "")
        (out / "manifest.json").write_text(json.dumps(man, indent=2) + "\n")
        run_fit_image(out / "manifest.json", out / "fit")
    except BaseException:
        shutil.rmtree(out)  # only what this script made
        raise
    return json.loads((out / "fit" / "result.json").read_text())


def write_comparison(path: Path, title: str, star: dict, got: dict, copy: str,
                     expected=None, expected_label: str = "") -> None:
    """Writes (and prints) ``path``: a Markdown table of every free parameter, the star's
    fit, ``expected(name, star_value)`` under ``expected_label`` if given (else the star's
    value is what the copy should give), the copy's fit, their difference and that in the
    star's standard errors; then both fits' residual RMS / peak and χ²/dof."""
    cols = ["parameter", "star"] + ([expected_label] if expected else []) + [
        copy, "difference", "difference / standard error"]
    lines = [title, "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for k in star["free"]:
        if k not in got["values"]:
            continue
        v = star["values"][k]
        want = expected(k, v) if expected else v
        d = got["values"][k] - want
        se = star["errors"].get(k) or float("nan")
        cells = [k, f"{v:.6g}"] + ([f"{want:.6g}"] if expected else []) + [
            f"{got['values'][k]:.6g}", f"{d:+.4g}", f"{d / se:+.3f}"]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", f"Residual RMS / peak: star {100 * star['residual_rms_over_peak']:.3f} %, "
              f"{copy} {100 * got['residual_rms_over_peak']:.3f} %; χ²/dof "
              f"{star['chi2_dof']:.4g}, {got['chi2_dof']:.4g}."]
    path.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
