"""The HTML reports in a real browser (issue 19): the fleet report and the doctor's report opened by headless
Chromium (Debian's package, installed by `make browser`, which `make test` runs): the page renders, its plots are
visible in the screenshot (their marker colours are there), and the browser logs no console message (the pages
have no scripts; a broken image or an error would show)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.fleet import fleet_report, generate_fleet, report_html, template_path

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium is not installed (make browser)")


def _screenshot(page: Path, png: Path, height: int = 1600) -> tuple[np.ndarray, str]:
    """Render ``page`` with headless Chromium; returns the screenshot (H, W, 3/4 floats) and the browser's log."""
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", f"--window-size=1200,{height}",
           f"--screenshot={png}", "--enable-logging=stderr", "--v=0", page.resolve().as_uri()]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert png.is_file(), res.stderr[-2000:]
    import matplotlib.image as mpimg

    return mpimg.imread(str(png)), res.stderr


def _has_colour(img: np.ndarray, hex_colour: str, tol: float = 0.08, min_pixels: int = 20) -> bool:
    rgb = np.array([int(hex_colour[i:i + 2], 16) / 255.0 for i in (1, 3, 5)])
    close = np.all(np.abs(img[..., :3] - rgb) < tol, axis=-1)
    return int(close.sum()) >= min_pixels


def _console(log: str) -> list[str]:
    return [line for line in log.splitlines() if "CONSOLE" in line]


def test_fleet_report_renders_with_its_plot(tmp_path):
    net = tnn_dsl.load(template_path())
    rng = np.random.default_rng(1)
    rows = [{"unit": f"b{i:02d}", "status": "ok", "val_mae": 0.016, "gain": 1.0, "findings": [],
             "params": {p: {"estimate": v * (1 + rng.uniform(-0.1, 0.1)) * (0.6 if (i, p) == (4, "U2") else 1.0),
                            "se": 1e-6, "status": "ok", "unit_si": "W/K"} for p, v in (("U1", 0.02), ("U2", 0.02))}}
            for i in range(12)]
    rep = fleet_report(rows, net)
    assert rep["outliers"]
    page = tmp_path / "report.html"
    page.write_text(report_html(rep), encoding="utf-8")
    img, log = _screenshot(page, tmp_path / "fleet.png")
    assert img.shape[0] >= 1000 and img.shape[1] >= 1000
    assert _has_colour(img, "#94aad0", tol=0.1)  # the fleet's points (#4c72b0 at alpha 0.6 on white)
    assert _has_colour(img, "#c44e52")  # the outlier's marker
    assert not (img[..., :3] > 0.97).all()  # not a blank page
    assert _console(log) == [], _console(log)


def test_doctor_report_renders_with_its_plots(tmp_path):
    from tnn_dsl.doctor import diagnose, write_report

    fl = tmp_path / "fleet"
    generate_fleet(fl, n_units=1, n_faulty=1, n_train=400, n_val=200, kinds=("sensor_lag",))
    d = diagnose(template_path(), [str(fl / "board-000" / "train.csv")], val=[str(fl / "board-000" / "val.csv")],
                 top=2, max_rounds=1, mlp_check=False)
    out = Path(write_report(d, tmp_path / "doctor"))
    page = out if out.suffix == ".html" else out / "index.html"
    img, log = _screenshot(page, tmp_path / "doctor.png", height=3000)
    assert not (img[..., :3] > 0.97).all()
    assert _has_colour(img, "#1f77b4", tol=0.1, min_pixels=200)  # matplotlib's first line colour: the plots drew
    assert _console(log) == [], _console(log)
