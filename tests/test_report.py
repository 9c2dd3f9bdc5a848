"""report.html: self-contained, and rendered by a real headless Chromium with every figure.

Chromium comes from the distribution (Debian package ``chromium``); CI installs it. Without
it this test FAILS (it does not skip): the report is the technician's view of a run and
must be checked in a browser.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from commission.cli import main
from commission.ident.hybrid import identify
from commission.mcaplog import read_config, read_recording
from commission.report import REPORT_NAME, render_report, search_history, true_plant_from_config, write_report

FIGURES = ["fig-bode", "fig-time", "fig-zoom", "fig-search", "fig-iterations"]
TUNING_FIGURES = ["fig-openloop", "fig-steps"]
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--hide-scrollbars", "--mute-audio",
]

# Runs in the page after load: the laid-out size of every figure's SVG and what it draws.
PROBE = """
<script>
(function () {
  var errors = [];
  window.addEventListener('error', function (e) { errors.push(String(e.message)); });
  function probe() {
    var out = {errors: errors, figures: {}};
    document.querySelectorAll('figure.plot').forEach(function (fig) {
      var svg = fig.querySelector('svg');
      var r = svg ? svg.getBoundingClientRect() : {width: 0, height: 0};
      var b = svg ? svg.getBBox() : {width: 0, height: 0};
      out.figures[fig.id] = {
        width: r.width, height: r.height, bboxWidth: b.width, bboxHeight: b.height,
        isSvg: !!svg && svg instanceof SVGSVGElement,
        paths: svg ? svg.querySelectorAll('path').length : 0,
        texts: svg ? svg.querySelectorAll('text').length : 0,
        caption: (fig.querySelector('figcaption') || {textContent: ''}).textContent.length
      };
    });
    var pre = document.createElement('pre');
    pre.id = 'probe-result';
    pre.textContent = JSON.stringify(out);
    document.body.appendChild(pre);
  }
  if (document.readyState === 'complete') probe(); else window.addEventListener('load', probe);
})();
</script>
"""


def _chromium() -> str:
    for name in (os.environ.get("CHROMIUM"), "chromium", "chromium-browser", "google-chrome"):
        if name and shutil.which(name):
            return shutil.which(name)  # type: ignore[return-value]
    pytest.fail(
        "Chromium is not installed: the report test needs a real browser. "
        "Install it with `apt-get update && apt-get install -y chromium` (as root), "
        "or set CHROMIUM=/path/to/chromium."
    )


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("run")
    assert main(["--sim", "--out", str(out), "--json", "--no-identify"]) == 0
    log = out / "run.mcap"
    recording = read_recording(log)
    config = read_config(log)
    return out, log, recording, config, identify(recording)


# controller.json's shape (commission.tuning.export.controller_json), with step responses
TUNING = {
    "sample_rate_hz": 8000.0,
    "velocity_loop": {"gain": 0.02, "gain_unit": "N·m·s/rad", "integral_gain": 2.0, "integral_time_s": 0.01,
                      "bandwidth_hz": 40.0},
    "position_loop": {"gain_per_s": 50.0, "bandwidth_hz": 7.96},
    "torque_filter": {"time_constant_s": 2e-4},
    "notch": [{"frequency_hz": 65.0, "q": 1.0, "depth_db": -20.0, "depth": 0.1}],
    "backlash_compensation": {"enabled": True, "amount_deg": 0.8, "epsilon_rad": 0.00698},
    "margins": {"phase_margin_deg": 55.0, "gain_margin_db": 9.0, "crossover_hz": 30.0, "phase_crossover_hz": 120.0,
                "stable": True},
    "drive_model": {"current_loop_bandwidth_hz": 2000.0, "computation_delay_samples": 1},
    "verification": {
        "ready": True, "reasons": [],
        "runs": {"proposed": {"step": {"overshoot_pct": 4.2, "settling_time_s": 0.03}}},
        "step_responses": {
            "with_compensation": {"t_s": [0.0, 0.01, 0.02, 0.05], "velocity_rad_s": [0.0, 0.6, 0.9, 1.0]},
            "without_compensation": {"t_s": [0.0, 0.01, 0.02, 0.05], "velocity_rad_s": [0.0, 0.8, 1.2, 1.0]},
        },
    },
}


@pytest.fixture(scope="module")
def report(run) -> Path:
    out, log, recording, config, ident = run
    path = write_report(out, recording, ident, config=config, source_file=log,
                        files=[log, out / "result.json"])
    assert path == out / REPORT_NAME
    return path


def _render(page: Path, tmp_path: Path) -> tuple[dict, Path]:
    """Load ``page`` (plus the probe) in headless Chromium: (probe result, screenshot)."""
    chromium = _chromium()
    probed = tmp_path / "probed.html"
    probed.write_text(page.read_text(encoding="utf-8").replace("</body>", PROBE + "</body>"), encoding="utf-8")
    common = [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}", "--window-size=1200,9000"]
    dom = subprocess.run([*common, "--virtual-time-budget=10000", "--dump-dom", probed.as_uri()],
                         capture_output=True, text=True, timeout=120)
    assert dom.returncode == 0, f"chromium --dump-dom failed: {dom.stderr[-2000:]}"
    found = re.search(r'<pre id="probe-result">(.*?)</pre>', dom.stdout, re.S)
    assert found, "the page did not finish loading in Chromium (no probe result in the DOM)"
    result = json.loads(found.group(1).replace("&amp;", "&").replace("&lt;", "<").replace("&gt;", ">").replace("&quot;", '"'))
    shot = tmp_path / "report.png"
    done = subprocess.run([*common, f"--screenshot={shot}", page.as_uri()], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and shot.exists(), f"chromium --screenshot failed: {done.stderr[-2000:]}"
    keep = os.environ.get("REPORT_SCREENSHOT_DIR")
    if keep:
        Path(keep).mkdir(parents=True, exist_ok=True)
        shutil.copy(shot, Path(keep) / f"{page.stem}.png")
    return result, shot


def _assert_figures(result: dict, expected: list[str]) -> None:
    assert result["errors"] == []
    missing = [f for f in expected if f not in result["figures"]]
    assert not missing, f"figures missing from the page: {missing}"
    for fig_id in expected:
        fig = result["figures"][fig_id]
        assert fig["isSvg"], fig_id
        assert fig["width"] > 600 and fig["height"] > 150, (fig_id, fig)   # laid out, not collapsed
        assert fig["bboxWidth"] > 100 and fig["bboxHeight"] > 100, (fig_id, fig)  # draws something
        assert fig["paths"] > 8 and fig["texts"] > 5, (fig_id, fig)        # lines, axes and labels
        assert fig["caption"] > 20, fig_id


def _assert_not_blank(shot: Path) -> None:
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("L"))
    assert img.shape[0] >= 1000 and img.shape[1] >= 1000
    top = img[: img.shape[0] // 2]
    assert top.std() > 10, "the screenshot is (nearly) blank"
    assert (top < 100).mean() > 0.002, "no dark pixels (text, lines) in the screenshot"


def test_report_is_self_contained(report: Path) -> None:
    text = report.read_text(encoding="utf-8")
    assert text.startswith("<!DOCTYPE html>")
    assert "<script" not in text and "<link" not in text and "<img" not in text and "<iframe" not in text
    assert not re.search(r"\ssrc=", text)
    hrefs = re.findall(r'href="([^"]*)"', text)
    assert hrefs and all(h.startswith("#") for h in hrefs), [h for h in hrefs if not h.startswith("#")][:5]
    assert "@import" not in text and not re.search(r"url\((?!#)", text)
    for fig_id in FIGURES:
        assert f'<figure class="plot" id="{fig_id}"><svg' in text, fig_id
    assert text.count("<svg") == len(FIGURES)
    # ids inside the inline SVGs do not collide between figures
    ids = re.findall(r'\sid="([^"]+)"', text)
    assert len(ids) == len(set(ids))
    assert 'id="tuning-placeholder"' in text


def test_report_says_what_the_run_found(run, report: Path) -> None:
    out, log, recording, config, ident = run
    text = report.read_text(encoding="utf-8")
    assert f"{ident.epsilon_deg:.4f}°" in text
    assert f"{ident.modes.f_resonance_hz:.2f} Hz" in text and f"{ident.modes.f_antiresonance_hz:.2f} Hz" in text
    assert "true plant (simulator)" in text  # a --sim run: the true plant is drawn
    assert str(log) in text and "drive-commission" in text and "SIM-0001" in text
    assert "configuration" in text and "excitation" in text


def test_report_renders_every_figure_in_chromium(report: Path, tmp_path: Path) -> None:
    result, shot = _render(report, tmp_path)
    _assert_figures(result, FIGURES)
    _assert_not_blank(shot)


def test_report_with_tuning_and_search_history_renders_in_chromium(run, tmp_path: Path) -> None:
    out, log, recording, config, ident = run
    history = [{"epsilon_deg": e, "phi": p, "omega_scale": 1.0, "cost_nm": 1e-3 + abs(e - 0.4) * (1 + p)}
               for p in (0.2, 0.5, 0.8) for e in np.linspace(0.0, 1.0, 21)]
    stages = [dataclasses.replace(s, detail={**s.detail, "history": history}) if s.name == "search" else s
              for s in ident.stages]
    ident_h = dataclasses.replace(ident, stages=stages)
    assert len(search_history(ident_h)) == len(history)
    page = write_report(tmp_path / "tuned.html", recording, ident_h, config=config, source_file=log, tuning=TUNING)
    text = page.read_text(encoding="utf-8")
    assert "tuning-placeholder" not in text and "phase margin" in text and "gain margin" in text
    assert "phase_margin_deg" in text and "without compensation" in text
    assert "63 evaluations" in text
    result, shot = _render(page, tmp_path)
    _assert_figures(result, FIGURES + TUNING_FIGURES)
    _assert_not_blank(shot)


def test_report_without_identification(run, tmp_path: Path) -> None:
    """--no-identify (or a failed identification): measured data only, still a page."""
    out, log, recording, config, ident = run
    text = render_report(recording, None, config=config, source_file=log)
    assert 'id="fig-bode"' in text and 'id="fig-time"' in text and 'id="fig-zoom"' in text
    assert 'id="fig-search"' not in text and "No identification" in text


def test_true_plant_only_for_simulated_drives(run) -> None:
    out, log, recording, config, ident = run
    tm, eps = true_plant_from_config(config, recording)
    assert math.isclose(math.degrees(eps), 0.4) and tm.K > 0
    real = recording.replace(drive=dataclasses.replace(recording.drive, backend="canopen", product="Σ-7", vendor="YASKAWA"))
    assert true_plant_from_config(config, real) is None
    assert true_plant_from_config(None, recording) is None
