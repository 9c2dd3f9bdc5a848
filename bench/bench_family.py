"""The identifier on the plant family (sim_drive.family, issue 22): accuracy, calibration, speed.

Every member is simulated, then identified by ``commission.ident.hybrid.identify`` in this
process, one after the other (time.perf_counter around ``identify`` only; the simulation is
not counted). The identifier gets its default options, as a user runs it: it takes the band,
the resolution and the residual's low-pass from the record (:func:`options_for`). Printed: the share within tolerance
(ε within ±0.01° or 2 % of ε, whichever is larger; J_m, J_l, K ±2 %; resonance and
anti-resonance ±0.5 %), flagged approximate (result.json ``fit.approximate``), silently
wrong (not flagged, outside tolerance), no result at all (by reason), the coverage of the
95 % ε interval, the median and 95th-percentile time and model evaluations (these do not move
with the machine's load or hour, where times do), breakdowns by class, and the worst members. A
dated summary is appended to bench/results/family.md.

    python bench/bench_family.py                    # default: the first 50 members, ~30 min (flagged ones are slow)
    python bench/bench_family.py --subset 1         # the whole family (200 members)
    python bench/bench_family.py --subset 1 --jobs 2 --out run.jsonl   # accuracy only, faster
    python bench/bench_family.py --compare bench/results/family-baseline.jsonl --out new.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import re
import signal
import subprocess
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Iterable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

# The identifier under test, and the one place that reads its result (_estimates).
from commission.ident.hybrid import IdentificationOptions, identify
from sim_drive.family import DEFAULT_SEED, DEFAULT_SIZE, Member, member

RESULTS = Path(__file__).resolve().parent / "results" / "family.md"
DEFAULT_SUBSET = 4
"""Every k-th member by default (``make bench``): with today's identifier the whole family takes
about half an hour sequentially on 2 cores (bench/results/family.md has the measured runs)."""

EPS_TOL_DEG = 0.01
EPS_TOL_REL = 0.02
PARAM_TOL_REL = 0.02
MODE_TOL_REL = 0.005
VERDICTS = ("within", "approximate", "silently_wrong", "no_result")
_VERDICT_TEXT = {"within": "within tolerance, not flagged", "approximate": "flagged approximate",
                 "silently_wrong": "SILENTLY WRONG (not flagged, outside tolerance)",
                 "no_result": "no result"}


def options_for(m: Member, resolution_from_duration: bool = False) -> IdentificationOptions:
    """The identifier's options for a member: the defaults, as a user runs it (the identifier takes
    the band and the resolution from the record); optionally an FRD resolution of 1/duration."""
    if resolution_from_duration:
        return IdentificationOptions(resolution_hz=max(0.1, 1.0 / m.duration_s))
    return IdentificationOptions()


def _estimates(result: Any) -> dict[str, Any]:
    """What the benchmark reads from an identification: its result.json document."""
    d = result.to_dict()
    est = dict(d["two_mass"])
    est["epsilon_deg"] = d["backlash"]["epsilon_deg"]
    est["f_resonance_hz"] = d["modes"]["f_resonance_hz"]
    est["f_antiresonance_hz"] = d["modes"]["f_antiresonance_hz"]
    fit = d.get("fit", {})
    return {"estimate": est, "interval_deg": list(d["backlash"]["epsilon_interval_deg"]),
            "approximate": bool(fit.get("approximate", False)), "residual_ratio": fit.get("residual_ratio"),
            "detected": bool(d["backlash"].get("detected", True)), "fit": fit,
            "relative_stderr": d.get("two_mass_relative_stderr")}


def judge(truth: dict[str, Any], est: dict[str, Any]) -> dict[str, Any]:
    """Errors (ε in degrees, the rest relative) and which are within tolerance."""
    eps = truth["epsilon_deg"]
    errors = {"epsilon_deg": est["epsilon_deg"] - eps}
    within = {"epsilon_deg": abs(errors["epsilon_deg"]) <= max(EPS_TOL_DEG, EPS_TOL_REL * eps)}
    true_vals = {**truth["two_mass"], **truth["modes"]}
    for k, tol in (("J_m", PARAM_TOL_REL), ("J_l", PARAM_TOL_REL), ("K", PARAM_TOL_REL),
                   ("f_resonance_hz", MODE_TOL_REL), ("f_antiresonance_hz", MODE_TOL_REL)):
        errors[k] = est[k] / true_vals[k] - 1.0
        within[k] = bool(abs(errors[k]) <= tol)
    for k in ("B_m", "B_l", "D"):  # reported, not judged (the tolerance names J, K, modes)
        errors[k] = est[k] / true_vals[k] - 1.0 if true_vals[k] else math.nan
    return {"errors": errors, "within": within}


#: A start (the frequency-domain one, or the encoders') this close to the truth in J_m, J_l and K is "near".
START_NEAR_REL = 0.2


def start_errors(result: Any, truth: dict[str, Any]) -> dict[str, float] | None:
    """The start stage's J_m, J_l, K relative to the truth (None: the stage is not in the result)."""
    try:
        start = result.stage("start").detail.get("parameters")
    except KeyError:  # the paper pipeline has no start stage
        return None
    if not start:
        return None
    return {k: start[k] / truth["two_mass"][k] - 1.0 for k in ("J_m", "J_l", "K")}


def evaluate(seed: int, index: int, resolution_from_duration: bool = False) -> dict[str, Any]:
    """Simulate and identify one member; the JSON line of the benchmark."""
    return evaluate_member(member(seed, index), resolution_from_duration)


def evaluate_member(m: Member, resolution_from_duration: bool = False) -> dict[str, Any]:
    """Simulate and identify ``m`` (a family member, or one recorded otherwise); the JSON line of the benchmark."""
    truth = m.to_dict()
    row: dict[str, Any] = {"id": m.id, "index": m.index, "classes": m.classes(), "label": label(m), "true": truth}
    rec = m.simulate()
    opts = options_for(m, resolution_from_duration)
    t0 = time.perf_counter()
    try:
        result = identify(rec, opts)
    except Exception as err:  # any failure is a result of the benchmark: no result, with its reason
        row.update(time_s=time.perf_counter() - t0, error=f"{type(err).__name__}: {err}",
                   verdict="no_result", covered=False)
        return row
    row["time_s"] = time.perf_counter() - t0
    row["error"] = None
    row["evaluations"] = int(result.evaluations)
    row["stages_s"] = {s.name: round(s.seconds, 3) for s in result.stages}
    row["restarts"] = next((s.detail.get("starts") for s in result.stages if s.name == "restarts"), None)
    row["delays"] = next((s.detail.get("tried") for s in result.stages if s.name == "delay"), None)
    row["notes"] = list(result.notes)
    row["start_errors"] = start_errors(result, truth)
    row.update(_estimates(result))
    row.update(judge(truth, row["estimate"]))
    lo, hi = row["interval_deg"]
    row["covered"] = bool(lo <= truth["epsilon_deg"] <= hi)
    ok = all(row["within"].values())
    row["within_tolerance"] = ok
    row["verdict"] = "approximate" if row["approximate"] else ("within" if ok else "silently_wrong")
    return row


def label(m: Member) -> str:
    """One line saying what the member is."""
    md, p = m.modes, m.two_mass
    peak = m.peak_torque_nm
    parts = [f"{m.sample_rate_hz / 1000:g} kHz {m.duration_s:g} s {m.sensors.value}",
             f"f_r {md.f_resonance_hz:.0f} Hz ζ {md.zeta_resonance:.3f}", f"J_l/J_m {p.J_l / p.J_m:.2g}",
             f"ε {m.epsilon_deg:.3f}°"]
    fc = m.coulomb_motor_nm + m.coulomb_load_nm
    if fc > 0:
        parts.append(f"Coulomb {100 * fc / peak:.1f} %")
    if m.current_loop_bandwidth_hz is not None:
        parts.append(f"loop {m.current_loop_bandwidth_hz:.0f} Hz")
    if m.torque_noise_nm > 0:
        parts.append(f"noise {100 * m.torque_noise_nm / peak:.2f} %")
    parts.append(f"{m.encoder_bits_motor}-bit")
    return ", ".join(parts)


# ----------------------------------------------------------------------------------------------
# summaries
# ----------------------------------------------------------------------------------------------
def _pct(n: int, d: int) -> str:
    return f"{100.0 * n / d:5.1f} %" if d else "    – "


def _percentile(xs: list[float], q: float) -> float:
    return float(np.percentile(xs, q)) if xs else math.nan


def reason(error: str) -> str:
    """An error message with its numbers blanked, to group failures."""
    return re.sub(r"[-+]?\d+(\.\d+)?(e[-+]?\d+)?", "#", error)[:140]


def summary(rows: list[dict[str, Any]], timing_note: str) -> list[str]:
    """The headline table."""
    n = len(rows)
    verdicts = Counter(r["verdict"] for r in rows)
    results = [r for r in rows if r["verdict"] != "no_result"]
    within = [r for r in results if r["within_tolerance"]]
    within_flagged = sum(1 for r in within if r["approximate"])
    covered = sum(1 for r in results if r["covered"])
    times = [r["time_s"] for r in results]
    all_times = [r["time_s"] for r in rows]
    out = [f"members: {n}",
           f"within tolerance (all results)   {len(within):4d}  {_pct(len(within), n)}"
           f"   (of which flagged approximate: {within_flagged})"]
    for v in VERDICTS:
        out.append(f"  {_VERDICT_TEXT[v]:<46} {verdicts[v]:4d}  {_pct(verdicts[v], n)}")
    out.append(f"95 % ε interval holds the truth   {covered:4d} of {len(results)} results  "
               f"{_pct(covered, len(results))}")
    # a flagged result the record does not determine reports ε anywhere in the searched range: the
    # coverage of the results that claim a narrow interval is the one that tests the statistics
    sharp = [r for r in results if not r["approximate"]]
    sharp_covered = sum(1 for r in sharp if r["covered"])
    out.append(f"  of the results not flagged      {sharp_covered:4d} of {len(sharp)}  {_pct(sharp_covered, len(sharp))}")
    out.append(f"time per identification [s] ({timing_note}): median {_percentile(times, 50):.2f}, "
               f"95th percentile {_percentile(times, 95):.2f}, max {max(times, default=math.nan):.2f} "
               f"(results only; every member, failures too: median {_percentile(all_times, 50):.2f}, "
               f"95th percentile {_percentile(all_times, 95):.2f})")
    counted = [r["evaluations"] for r in results if "evaluations" in r]
    if counted:
        # unmoved by the machine's load and hour, where times are not: compares two versions of the identifier
        out.append(f"model evaluations per identification (the fits' simulations and predictor passes): median "
                   f"{_percentile(counted, 50):.0f}, 95th percentile {_percentile(counted, 95):.0f}, "
                   f"sum {sum(counted)}")
    failures = Counter(reason(r["error"]) for r in rows if r["verdict"] == "no_result")
    if failures:
        out.append("no result, by reason:")
        out += [f"  {c:4d}  {msg}" for msg, c in failures.most_common()]
    out += _by_start(rows)
    out.append("out of tolerance, by quantity (results): " + ", ".join(
        f"{k} {sum(1 for r in results if not r['within'][k])}"
        for k in ("epsilon_deg", "J_m", "J_l", "K", "f_resonance_hz", "f_antiresonance_hz")))
    return out


def _by_start(rows: list[dict[str, Any]]) -> list[str]:
    """Verdicts by how near the start was to the truth: what a better start would buy."""
    known = [r for r in rows if r.get("start_errors")]
    if not known:
        return []
    out = [f"by the start's distance to the truth (J_m, J_l, K; {len(known)} members with a start):"]
    groups: dict[bool, list[dict[str, Any]]] = {True: [], False: []}
    for r in known:
        groups[max(abs(v) for v in r["start_errors"].values()) <= START_NEAR_REL].append(r)
    for name, group in ((f"within {100 * START_NEAR_REL:.0f} %", groups[True]), ("further off", groups[False])):
        v = Counter(r["verdict"] for r in group)
        out.append(f"  start {name:<16} {len(group):4d}: " + (", ".join(
            f"{k.replace('_', ' ')} {v[k]}" for k in VERDICTS if v[k]) or "none"))
    return out


def breakdown(rows: list[dict[str, Any]]) -> list[str]:
    """Per class of every dimension: shares of the four verdicts, coverage, median time."""
    out = [f"{'dimension':<17} {'class':<16} {'n':>4} {'within':>7} {'approx':>7} {'silent':>7} "
           f"{'none':>7} {'cover':>7} {'t med':>6}"]
    dims = list(rows[0]["classes"]) if rows else []
    for dim in dims:
        groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
        for r in rows:
            groups[r["classes"][dim]].append(r)
        for cls in sorted(groups, key=_class_order):
            g = groups[cls]
            v = Counter(r["verdict"] for r in g)
            res = [r for r in g if r["verdict"] != "no_result"]
            cov = sum(1 for r in res if r["covered"])
            t = _percentile([r["time_s"] for r in res], 50)
            out.append(f"{dim:<17} {cls:<16} {len(g):4d} " + " ".join(_pct(v[k], len(g)) for k in VERDICTS)
                       + f" {_pct(cov, len(res))} {t:6.2f}")
            dim = ""
    return out


def _class_order(cls: str) -> tuple[float, str]:
    """Numeric classes in numeric order ("2 kHz" before "10 kHz", "< x" first, "≥ x" last)."""
    if cls in ("none", "ideal"):
        return (-math.inf, cls)
    m = re.search(r"\d+(\.\d+)?", cls)
    v = float(m.group()) if m else math.inf
    return (v + (0.5 if cls.startswith("≥") else 0.0) - (0.5 if cls.startswith("<") else 0.0), cls)


def severity(r: dict[str, Any]) -> float:
    """How wrong a member's outcome is (larger: worse); no result ranks above everything."""
    if r["verdict"] == "no_result":
        return math.inf
    tol = {"epsilon_deg": max(EPS_TOL_DEG, EPS_TOL_REL * r["true"]["epsilon_deg"]), "J_m": PARAM_TOL_REL,
           "J_l": PARAM_TOL_REL, "K": PARAM_TOL_REL, "f_resonance_hz": MODE_TOL_REL,
           "f_antiresonance_hz": MODE_TOL_REL}
    worst = max(abs(r["errors"][k]) / t for k, t in tol.items())
    return worst * (2.0 if r["verdict"] == "silently_wrong" else 1.0)


def what_went_wrong(r: dict[str, Any]) -> str:
    if r["verdict"] == "no_result":
        return r["error"]
    e = r["errors"]
    bad = [f"ε {e['epsilon_deg']:+.3f}°" if k == "epsilon_deg" else f"{_short(k)} {100 * e[k]:+.2f} %"
           for k, ok in r["within"].items() if not ok]
    flags = "approximate" if r["approximate"] else ("silently wrong" if bad else "within")
    cov = "" if r["covered"] else (f", interval [{r['interval_deg'][0]:.4f}, {r['interval_deg'][1]:.4f}]° "
                                   "misses ε")
    return f"{flags}: " + (", ".join(bad) or "all within") + cov


def _same(a: Any, b: Any) -> bool:
    """Equal JSON values, floats within 1e-9 relative (another machine's libm may differ in the last bit)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, (int, float)) and not isinstance(b, bool):
        return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-300)
    return bool(a == b)


def _short(k: str) -> str:
    return {"f_resonance_hz": "f_r", "f_antiresonance_hz": "f_a"}.get(k, k)


def worst(rows: list[dict[str, Any]], count: int) -> list[str]:
    """Silently wrong members first (all), then per reason of no result a few examples, then the
    flagged members furthest off; a member is one line and what went wrong."""
    def line(r: dict[str, Any]) -> str:
        return f"  {r['id']}  {r['label']}\n           → {what_went_wrong(r)}"

    out = [line(r) for r in sorted((r for r in rows if r["verdict"] == "silently_wrong"), key=severity,
                                   reverse=True)]
    groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        if r["verdict"] == "no_result":
            groups[reason(r["error"])].append(r)
    per_reason = max(1, count // max(1, len(groups)))
    for g in sorted(groups.values(), key=len, reverse=True):
        out += [line(r) for r in g[:per_reason]]
        if len(g) > per_reason:
            out.append(f"           (same reason: {', '.join(r['id'] for r in g[per_reason:])})")
    flagged = sorted((r for r in rows if r["verdict"] == "approximate" and not r["within_tolerance"]),
                     key=severity, reverse=True)
    out += [line(r) for r in flagged[:count]]
    return out


def compare(old_rows: list[dict[str, Any]], new_rows: list[dict[str, Any]]) -> list[str]:
    """What changed between two runs, on the members both ran."""
    old = {r["id"]: r for r in old_rows}
    common = [r for r in new_rows if r["id"] in old]
    out = [f"compared on {len(common)} members both runs hold "
           f"({len(new_rows) - len(common)} new only, {len(old_rows) - len(common)} old only)"]
    changed_truth = [r["id"] for r in common if not _same(r["true"], old[r["id"]]["true"])]
    if changed_truth:
        out.append(f"WARNING: {len(changed_truth)} members have different true values (family changed): "
                   + ", ".join(changed_truth[:10]))
    before = Counter(old[r["id"]]["verdict"] for r in common)
    after = Counter(r["verdict"] for r in common)
    for v in VERDICTS:
        out.append(f"  {v:<15} {before[v]:4d} → {after[v]:4d}")
    cov_o = sum(1 for r in common if old[r["id"]]["covered"])
    cov_n = sum(1 for r in common if r["covered"])
    out.append(f"  interval holds truth {cov_o:4d} → {cov_n:4d}")
    to = [old[r["id"]]["time_s"] for r in common if old[r["id"]]["verdict"] != "no_result"]
    tn = [r["time_s"] for r in common if r["verdict"] != "no_result"]
    out.append(f"  median time {_percentile(to, 50):.2f} → {_percentile(tn, 50):.2f} s, 95th percentile "
               f"{_percentile(to, 95):.2f} → {_percentile(tn, 95):.2f} s")
    counted = [(old[r["id"]]["evaluations"], r["evaluations"]) for r in common
               if "evaluations" in r and "evaluations" in old[r["id"]]]
    if counted:
        eo, en = zip(*counted)
        out.append(f"  model evaluations on {len(counted)} members: median "
                   f"{_percentile(list(eo), 50):.0f} → {_percentile(list(en), 50):.0f}, sum {sum(eo)} → {sum(en)}")
    both = [(old[r["id"]], r) for r in common if "estimate" in r and "estimate" in old[r["id"]]]
    d_eps = [abs(n["estimate"]["epsilon_deg"] - o["estimate"]["epsilon_deg"]) for o, n in both]
    d_rel = [max(abs(n["estimate"][k] / o["estimate"][k] - 1.0) for k in ("J_m", "J_l", "K")) for o, n in both]
    moved = sum(1 for e, p in zip(d_eps, d_rel) if e > 1e-4 or p > 1e-4)
    out.append(f"  estimates moved (ε by > 1e-4° or J_m, J_l, K by > 1e-4 relative): {moved} of {len(both)} "
               f"members with a result in both; largest |Δε| {max(d_eps, default=0.0):.4f}°, largest relative "
               f"J/K change {100 * max(d_rel, default=0.0):.2f} %")
    moves = Counter((old[r["id"]]["verdict"], r["verdict"]) for r in common
                    if old[r["id"]]["verdict"] != r["verdict"])
    if moves:
        out.append("verdict changes: " + ", ".join(f"{a} → {b}: {c}" for (a, b), c in moves.most_common()))
    for r in common:
        o = old[r["id"]]
        if o["verdict"] != r["verdict"]:
            out.append(f"  {r['id']}  {o['verdict']} → {r['verdict']}: {what_went_wrong(r)}  ({r['label']})")
    return out


# ----------------------------------------------------------------------------------------------
# running
# ----------------------------------------------------------------------------------------------
def _run_all(seed: int, indices: list[int], jobs: int, adapt: bool) -> Iterable[dict[str, Any]]:
    """Members' results as they finish (with several processes a slow member does not hold back the
    others' lines); the summary sorts them."""
    if jobs == 1:
        for i in indices:
            yield evaluate(seed, i, adapt)
        return
    # each process compiles or loads the kernels before its first timed member, as the sequential run does
    pool = multiprocessing.get_context("spawn").Pool(jobs, initializer=_warm)
    try:
        yield from pool.imap_unordered(_evaluate, [(seed, i, adapt) for i in indices])
        pool.close()
    finally:
        # an interrupted bench (Ctrl-C, SIGTERM) stops its workers: they would run on to their members' ends
        pool.terminate()
        pool.join()


def _warm() -> None:
    evaluate(DEFAULT_SEED, 0, False)


def _evaluate(args: tuple[int, int, bool]) -> dict[str, Any]:
    return evaluate(*args)


def _git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             cwd=Path(__file__).resolve().parent, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, cwd=Path(__file__).resolve().parent).stdout.strip()
        return out + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    # SIGTERM as an exit, not an abrupt end: the worker processes are stopped on the way out
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED, help=f"family seed (default {DEFAULT_SEED})")
    ap.add_argument("--size", type=int, default=DEFAULT_SIZE, help=f"family size (default {DEFAULT_SIZE})")
    ap.add_argument("--members", type=int, default=None, help="run the first N members of the selection only")
    ap.add_argument("--subset", type=int, default=DEFAULT_SUBSET,
                    help=f"run the first 1/k of the family (default {DEFAULT_SUBSET}; 1 = the whole family); a "
                         "prefix of the Halton sequence is itself evenly spread, every k-th member is not "
                         "(every 4th had J_l/J_m ≥ 2 in 49 of 50)")
    ap.add_argument("--only", default=None, help="comma-separated member indices")
    ap.add_argument("--jobs", type=int, default=1,
                    help="processes (>1: for accuracy checks only, times are then not representative)")
    ap.add_argument("--resolution-from-duration", action="store_true",
                    help="give the identifier an FRD resolution of 1/duration on records under 10 s "
                         "(default: the identifier's own 0.1 Hz)")
    ap.add_argument("--out", type=Path, default=None, help="per-member results as JSON lines")
    ap.add_argument("--compare", type=Path, default=None, help="a previous --out file to compare with")
    ap.add_argument("--worst", type=int, default=15, help="worst members listed (default 15)")
    ap.add_argument("--no-record", action="store_true", help=f"do not append to {RESULTS}")
    args = ap.parse_args(argv)
    if args.subset < 1 or args.jobs < 1 or args.size < 1:
        ap.error("--subset, --jobs and --size must be ≥ 1")
    if args.only:
        try:
            indices = sorted({int(s) for s in args.only.split(",")})
        except ValueError:
            ap.error("--only takes comma-separated integers")
    else:
        indices = list(range(0, -(-args.size // args.subset)))
    if args.members is not None:
        indices = indices[:args.members]
    old_rows = _read_jsonl(args.compare) if args.compare else None

    timing = "sequential, in-process" if args.jobs == 1 else f"{args.jobs} processes: NOT representative"
    print(f"# family seed {args.seed}: {len(indices)} of {args.size} members"
          f"{f' (the first 1/{args.subset})' if args.subset > 1 and not args.only else ''}; {timing}; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; identifier commit {_git_commit()}")
    if args.jobs == 1:  # compile/load the kernels outside the timed calls
        _warm()
    t_start = time.perf_counter()
    rows: list[dict[str, Any]] = []
    out_file = args.out.open("w") if args.out else None
    try:
        for r in _run_all(args.seed, indices, args.jobs, args.resolution_from_duration):
            rows.append(r)
            if out_file:
                out_file.write(json.dumps(r) + "\n")
                out_file.flush()
            print(f"  {r['id']} {r['verdict']:<15} {r['time_s']:6.2f} s  {what_went_wrong(r)[:110]}", flush=True)
    finally:
        if out_file:
            out_file.close()
    elapsed = time.perf_counter() - t_start
    rows.sort(key=lambda r: r["index"])
    lines = [f"bench wall time {elapsed / 60:.1f} min (simulation included); load average at the end "
             f"{os.getloadavg()[0]:.1f} (wall times inflate with load)", *summary(rows, timing)]
    report = ["", *lines, "", "by class:", *breakdown(rows), "", "worst members:", *worst(rows, args.worst)]
    if old_rows is not None:
        report += ["", f"compared with {args.compare}:", *compare(old_rows, rows)]
    print("\n".join(report))
    if not args.no_record:
        _record(args, argv, len(indices), lines, breakdown(rows), worst(rows, 6))
    return 0


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    try:
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except (OSError, json.JSONDecodeError) as err:
        raise SystemExit(f"cannot read {path}: {err}") from err


def _record(args: argparse.Namespace, argv: list[str] | None, n: int, lines: list[str],
            table: list[str], worst_lines: list[str]) -> None:
    """Append the run's summary to the results file."""
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    cmd = " ".join(["python bench/bench_family.py", *(sys.argv[1:] if argv is None else argv)])
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    block = [f"## {stamp} — identifier {_git_commit()}, seed {args.seed}, {n} members", "",
             f"`{cmd}` (load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)", "", "```",
             *lines, "", *table, "", "worst:", *worst_lines, "```", ""]
    with RESULTS.open("a") as f:
        f.write("\n".join(block) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
