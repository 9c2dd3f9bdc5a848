"""What following a flagged result's remedy does (issue 22): each family member the identifier flags is
simulated again with the one change a remedy in its ``fit.remedies`` names, and identified again.

Remedies followed: "record with a load encoder" (the member's sensors → motor and load encoders) and a named
"end the chirp at N Hz" (the excitation's ``f_end_hz`` → N, and its sample rate where the remedy names one).
Printed per remedy: how many of the members recorded again are within tolerance and not flagged, flagged, or
silently wrong (``bench_family.evaluate_member``), and their times. Not part of ``make bench`` (it identifies every
flagged member twice more: an hour on the 21 flagged members of seeds 22–24's first 96).

    python bench/remedies.py --from run.jsonl --jobs 2        # the flagged members of a bench_family --out file
    python bench/remedies.py --from run.jsonl --only 24:023   # one of them
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import re
import statistics
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_family import evaluate_member  # noqa: E402

from sim_drive.family import Member, Sensors, member  # noqa: E402

LOAD_ENCODER = "load encoder"
CHIRP_END = "chirp end"
_NAMED_END = re.compile(r"end the chirp at (\d+) Hz or more")
_NAMED_RATE = re.compile(r"sample rate of (\d+) Hz or more")


def followed(m: Member, remedy: str) -> tuple[str, Member] | None:
    """The member recorded as ``remedy`` asks (None: a remedy this script does not follow)."""
    if remedy.startswith("record with a load encoder"):
        return LOAD_ENCODER, dataclasses.replace(m, sensors=Sensors.LOAD_ENCODER)
    end = _NAMED_END.search(remedy)
    if end is None:  # the unnamed "3.5× the resonance": no frequency to record at
        return None
    rate = _NAMED_RATE.search(remedy)
    update = {"f_end_hz": float(end.group(1))}
    if rate is not None:
        update["sample_rate_hz"] = float(rate.group(1))
    return CHIRP_END, dataclasses.replace(m, excitation=m.excitation.model_copy(update=update))


def evaluate(job: tuple[str, Member]) -> dict[str, Any]:
    """One member recorded again as one remedy asks (``job``: the remedy's kind and the member), identified:
    ``bench_family``'s JSON line, with the remedy followed."""
    kind, m = job
    return {"remedy": kind, **evaluate_member(m)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--from", dest="source", type=Path, required=True,
                    help="a bench_family.py --out file: its flagged members and their remedies")
    ap.add_argument("--only", default=None, help="comma-separated member ids (e.g. 22:014,24:023)")
    ap.add_argument("--jobs", type=int, default=1, help="processes (each identification runs 2 threads)")
    ap.add_argument("--out", type=Path, default=None, help="per member and remedy, as JSON lines")
    args = ap.parse_args(argv)
    only = set(args.only.split(",")) if args.only else None
    jobs: list[tuple[str, Member]] = []
    for line in args.source.read_text().splitlines():
        row = json.loads(line)
        if row.get("verdict") != "approximate" or (only and row["id"] not in only):
            continue
        m = member(row["true"]["seed"], row["true"]["index"])
        for remedy in (row.get("fit") or {}).get("remedies", []):
            f = followed(m, remedy)
            if f is not None:
                jobs.append(f)
    if not jobs:
        print("no flagged member with a remedy this script follows", file=sys.stderr)
        return 1
    print(f"{len(jobs)} records to make and identify again ({args.jobs} processes)", file=sys.stderr)
    with multiprocessing.get_context("spawn").Pool(max(1, args.jobs)) as pool:
        rows = []
        for r in pool.imap_unordered(evaluate, jobs):
            rows.append(r)
            print(f"  {r['id']} {r['remedy']:<13} {r['verdict']:<15} {r['time_s']:7.1f} s", file=sys.stderr)
    if args.out:
        args.out.write_text("".join(json.dumps(r) + "\n" for r in rows))
    print(f"{'remedy followed':<16} {'members':>7} {'within':>7} {'flagged':>8} {'silently wrong':>15} "
          f"{'no result':>10} {'median s':>9}")
    for kind in (LOAD_ENCODER, CHIRP_END):
        rs = [r for r in rows if r["remedy"] == kind]
        if rs:
            n = {v: sum(r["verdict"] == v for r in rs) for v in ("within", "approximate", "silently_wrong", "no_result")}
            print(f"{kind:<16} {len(rs):>7} {n['within']:>7} {n['approximate']:>8} {n['silently_wrong']:>15} "
                  f"{n['no_result']:>10} {statistics.median(r['time_s'] for r in rs):>9.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
