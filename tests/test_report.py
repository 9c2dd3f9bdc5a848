"""report.html: self-contained, and rendered by a real headless Chromium with every figure.

Chromium comes from the distribution (Debian package ``chromium``); CI installs it. Without
it this test FAILS (it does not skip): the report is the technician's view of a run and
must be checked in a browser.
"""

from __future__ import annotations

import contextlib
import dataclasses
import html
import io
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
from commission.plant import PlantParameters
from commission.report import REPORT_NAME, render_report, search_history, write_report
from commission.sequencer import simulated_plant, tune_and_export
from commission.tuning import TuningOptions

FIGURES = ["fig-bode", "fig-time", "fig-zoom", "fig-search", "fig-iterations"]
TUNING_FIGURES = ["fig-openloop", "fig-step", "fig-move", "fig-reversal"]
ZOOMABLE = ["fig-bode", "fig-time", "fig-zoom", "fig-openloop", "fig-move", "fig-reversal"]
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
  // drag across the middle of the plot, then double-click: the x labels before, zoomed, reset
  function labels(svg) {
    var g = svg.querySelector('g.panel[data-labels="1"] g.xaxis');
    return Array.prototype.map.call(g.querySelectorAll('text'), function (n) { return n.textContent; });
  }
  function fire(svg, type, x, y) {
    var pt = svg.createSVGPoint(); pt.x = x; pt.y = y;
    var c = pt.matrixTransform(svg.getScreenCTM());
    svg.dispatchEvent(new MouseEvent(type, {clientX: c.x, clientY: c.y, bubbles: true, view: window}));
  }
  function zoom(svg) {
    var g = svg.querySelector('g.panel'), L = +g.dataset.left, R = +g.dataset.right, y = +g.dataset.top + 10;
    var out = {before: labels(svg)};
    fire(svg, 'mousedown', L + 0.3 * (R - L), y);
    fire(svg, 'mousemove', L + 0.6 * (R - L), y);
    fire(svg, 'mouseup', L + 0.6 * (R - L), y);
    out.zoomed = labels(svg);
    out.transform = svg.querySelector('g.data').getAttribute('transform');
    fire(svg, 'dblclick', L + 0.5 * (R - L), y);
    out.reset = labels(svg);
    return out;
  }
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
        caption: (fig.querySelector('figcaption') || {textContent: ''}).textContent.length,
        zoom: svg && svg.dataset.zoom ? zoom(svg) : null
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


@pytest.fixture(scope="module")
def report(run) -> Path:
    out, log, recording, config, ident = run
    path = write_report(out, recording, ident, config=config, source_file=log,
                        true_plant=simulated_plant(recording, config), files=[log, out / "result.json"])
    assert path == out / REPORT_NAME
    return path


@pytest.fixture(scope="module")
def tuned(run, tmp_path_factory: pytest.TempPathFactory):
    """A report with controller settings verified on the simulator's plant, and controller.json."""
    out, log, recording, config, ident = run
    folder = tmp_path_factory.mktemp("tuned")
    plant = simulated_plant(recording, config)
    tuning = tune_and_export(folder, ident, TuningOptions(), None, plant)
    check = {"epsilon_deg": 0.41, "spread_deg": 0.02, "reversals": 3, "log": str(folder / "backlash-check.mcap")}
    page = write_report(folder / REPORT_NAME, recording, ident, config=config, source_file=log, tuning=tuning,
                        true_plant=plant, backlash_check=check)
    return page, json.loads((folder / "controller.json").read_text(encoding="utf-8")), tuning


def _render(page: Path, tmp_path: Path) -> tuple[dict, Path]:
    """Load ``page`` (plus the probe) in headless Chromium: (probe result, screenshot)."""
    chromium = _chromium()
    probed = tmp_path / "probed.html"
    # the probe first in the body: it sees errors of the page's own script too
    probed.write_text(page.read_text(encoding="utf-8").replace("<body>", "<body>" + PROBE, 1), encoding="utf-8")
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
        assert fig["paths"] >= 3 and fig["texts"] > 5, (fig_id, fig)  # grid, frame and data; axis labels
        assert fig["caption"] > 20, fig_id
        if fig_id in ZOOMABLE:  # drag zooms the x axis (labels drawn again), double-click goes back
            z = fig["zoom"]
            assert z is not None, fig_id
            assert z["zoomed"] != z["before"] and "scale(" in z["transform"], (fig_id, z)
            assert z["reset"] == z["before"], (fig_id, z)


def _assert_not_blank(shot: Path) -> None:
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("L"))
    assert img.shape[0] >= 1000 and img.shape[1] >= 1000
    top = img[: img.shape[0] // 2]
    assert top.std() > 10, "the screenshot is (nearly) blank"
    assert (top < 100).mean() > 0.002, "no dark pixels (text, lines) in the screenshot"


def _assert_self_contained(text: str) -> None:
    assert text.startswith("<!DOCTYPE html>")
    # one inline script (the zoom), nothing loaded from elsewhere
    assert text.count("<script") <= 1 and "<script>" in text or "<script" not in text
    assert "<link" not in text and "<img" not in text and "<iframe" not in text
    assert not re.search(r"\ssrc=", text)
    assert not any(call in text for call in ("fetch(", "XMLHttpRequest", "import(", "https://"))
    hrefs = re.findall(r'href="([^"]*)"', text)
    assert hrefs and all(h.startswith("#") for h in hrefs), [h for h in hrefs if not h.startswith("#")][:5]
    assert "@import" not in text and not re.search(r"url\((?!#)", text)
    # ids inside the inline SVGs do not collide between figures
    ids = re.findall(r'\sid="([^"]+)"', text)
    assert len(ids) == len(set(ids))


def test_report_is_self_contained(report: Path) -> None:
    text = report.read_text(encoding="utf-8")
    _assert_self_contained(text)
    for fig_id in FIGURES:
        assert f'<figure class="plot" id="{fig_id}"><svg' in text, fig_id
    assert text.count("<svg") == len(FIGURES)
    assert "No controller settings in this run" in text  # the verdict says why there is none


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


def test_verdict_comes_first_and_the_header_names_the_model(run, tuned) -> None:
    out, log, recording, config, ident = run
    page, doc, _ = tuned
    text = page.read_text(encoding="utf-8")
    verdict = text.index('id="verdict"')
    assert verdict < text.index("<figure") and verdict < text.index("<table")
    ready = doc["verification"]["ready"]
    head = re.search(r'<section class="verdict ([a-z-]+)" id="verdict"><h2>([^<]*)</h2>', text)
    assert head and head.group(1) == ("ready" if ready else "not-ready")
    assert head.group(2).startswith("Ready" if ready else "Not ready")
    for reason in doc["verification"]["reasons"]:
        assert html.escape(reason) in text[verdict:text.index("<figure")]
    # the tiles, before the first figure: ε with its interval, J_m, J_l, K, the modes, the margins
    tiles = dict(re.findall(r'<div class="card" id="(tile-[a-z-]+)"><b>([^<]*)</b>', text))
    lo, hi = (math.degrees(x) for x in ident.epsilon_interval_rad)
    assert tiles["tile-epsilon"] == f"{ident.epsilon_deg:.4f}°" and f"[{lo:.4f}°, {hi:.4f}°]" in text
    for key, value in (("tile-jm", ident.parameters.J_m), ("tile-jl", ident.parameters.J_l),
                       ("tile-k", ident.parameters.K)):
        mantissa = float(re.match(r"[0-9.]+", tiles[key]).group(0))
        exponent = re.search(r"10([⁻⁰¹²³⁴⁵⁶⁷⁸⁹]+)", tiles[key])
        if exponent:
            mantissa *= 10.0 ** int(exponent.group(1).translate(str.maketrans("⁻⁰¹²³⁴⁵⁶⁷⁸⁹", "-0123456789")))
        assert mantissa == pytest.approx(value, rel=1e-3), key
    assert tiles["tile-resonance"] == f"{ident.modes.f_resonance_hz:.2f} Hz"
    assert tiles["tile-antiresonance"] == f"{ident.modes.f_antiresonance_hz:.2f} Hz"
    assert text.index('id="tile-gm"') < text.index("<figure")


def _lookup(doc: dict, key: str) -> float:
    node = doc
    for part in key.split("."):
        node = node[part]
    return node


def test_every_margin_on_the_page_is_controller_json(run, tuned) -> None:
    """One loop model: the tiles, the margins table and the open-loop plot show controller.json's margins."""
    ident = run[4]
    page, doc, tuning = tuned
    text = page.read_text(encoding="utf-8")
    tiles = dict(re.findall(r'<div class="card" id="(tile-[a-z-]+)"><b>([^<]*)</b>', text))
    assert tiles["tile-pm"] == f"{doc['margins']['phase_margin_deg']:.1f}°"
    assert tiles["tile-gm"] == f"{doc['margins']['gain_margin_db']:.1f} dB"
    cells = re.findall(r'<td class="num margin[^"]*" data-key="([^"]+)">([^<]*)</td>', text)
    keys = {k for k, _ in cells}
    assert {"margins.phase_margin_deg", "margins.gain_margin_db", "position_loop.margins.phase_margin_deg"} <= keys
    if doc["margins"]["gap"] is not None:
        assert "margins.gap.phase_margin_deg" in keys
    for key, shown in cells:
        unit = "°" if key.endswith("_deg") else " dB"
        assert shown == f"{_lookup(doc, key):.1f}{unit}", key
    # the open loop drawn is the design's: its legend names the same margins at the same frequencies
    fig = text[text.index('id="fig-openloop"'):]
    fig = fig[:fig.index("</figure>")]
    drawn_pm = [float(x) for x in re.findall(r"PM (-?[0-9.]+)°", fig)]
    drawn_gm = [float(x) for x in re.findall(r"GM (-?[0-9.]+) dB", fig)]
    expected_pm = [round(doc["margins"]["phase_margin_deg"], 1)]
    expected_gm = [round(doc["margins"]["gain_margin_db"], 1)]
    if doc["margins"]["gap"] is not None:
        expected_pm.append(round(doc["margins"]["gap"]["phase_margin_deg"], 1))
        expected_gm.append(round(doc["margins"]["gap"]["gain_margin_db"], 1))
    assert drawn_pm == expected_pm and drawn_gm == expected_gm
    # ... and the loop drawn crosses 0 dB where controller.json says, with that phase margin
    from commission.tuning import open_loop

    fc = doc["margins"]["crossover_hz"]
    L = open_loop(tuning.settings, ident.parameters, np.array([fc]))
    assert abs(L[0]) == pytest.approx(1.0, abs=1e-6)
    assert 180.0 - abs(math.degrees(np.angle(L[0]))) == pytest.approx(doc["margins"]["phase_margin_deg"], abs=1e-6)


def test_report_with_tuning_renders_in_chromium(tuned, tmp_path: Path) -> None:
    page, doc, _ = tuned
    text = page.read_text(encoding="utf-8")
    _assert_self_contained(text)
    # the verification as tables with units, no raw Python values
    ver = text[text.index('id="verification"'):text.index('id="model"')]
    assert "overshoot [%]" in ver and "settling time [ms]" in ver and "load error [mrad]" in ver
    assert "None" not in ver and "True" not in ver and "False" not in ver
    assert "velocity_step" not in ver and "proposed settings" in ver
    # the --measure-backlash result
    assert 'id="backlash-check"' in text and "0.4100" in text
    result, shot = _render(page, tmp_path)
    _assert_figures(result, FIGURES + TUNING_FIGURES)
    _assert_not_blank(shot)


def test_report_shows_the_search_history(run, tmp_path: Path) -> None:
    out, log, recording, config, ident = run
    history = [{"epsilon_deg": e, "phi": p, "omega_scale": 1.0, "cost_nm": 1e-3 + abs(e - 0.4) * (1 + p)}
               for p in (0.2, 0.5, 0.8) for e in np.linspace(0.0, 1.0, 21)]
    stages = [dataclasses.replace(s, detail={**s.detail, "history": history}) if s.name == "scan" else s
              for s in ident.stages]
    ident_h = dataclasses.replace(ident, stages=stages)
    assert len(search_history(ident_h)) == len(history)
    text = render_report(recording, ident_h, config=config, source_file=log)
    assert "63 evaluations" in text and "φ 0.5" in text


def test_report_without_identification(run, tmp_path: Path) -> None:
    """--no-identify (or a failed identification): measured data only, still a page."""
    out, log, recording, config, ident = run
    text = render_report(recording, None, config=config, source_file=log)
    assert 'id="fig-bode"' in text and 'id="fig-time"' in text and 'id="fig-zoom"' in text
    assert 'id="fig-search"' not in text and "No identification" in text
    assert text.index('id="verdict"') < text.index("<figure")


def test_the_plant_comes_from_the_run_not_from_the_drive_name(run) -> None:
    """A --sim run stores its plant in the log; a recording without it (a real drive, whatever its
    name says) has none."""
    out, log, recording, config, ident = run
    plant = simulated_plant(recording, config)
    assert plant == PlantParameters.model_validate(config["sim"] or {})
    assert "simulated_plant" in recording.metadata
    named = recording.replace(
        drive=dataclasses.replace(recording.drive, backend="canopen", product="simulated drive", vendor="SIM"),
        metadata={k: v for k, v in recording.metadata.items() if k != "simulated_plant"})
    assert simulated_plant(named, config) is None
    assert "true plant (simulator)" not in render_report(named, ident, config=config)


def test_measure_backlash_result_is_in_the_report(tmp_path: Path) -> None:
    """`commission --sim --measure-backlash`: the reversal check's ε is in report.html, as measured."""
    out = tmp_path / "run"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["--sim", "--measure-backlash", "--no-tune", "--out", str(out), "--json"]) == 0
    check = json.loads(buf.getvalue())["backlash_check"]
    text = (out / REPORT_NAME).read_text(encoding="utf-8")
    section = text[text.index('id="backlash-check"'):text.index('id="model"')]
    assert f"{check['epsilon_deg']:.4f}" in section and check["log"] in section
    assert text.count('id="backlash-check"') == 1
