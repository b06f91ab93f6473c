"""Two versions' `bench.quality` runs compared over several seeds, case by case.

    python -m bench.compare_quality --before old_0.json old_1.json ... --after new_0.json ...

Each file is one seed's ``python -m bench.quality --json FILE --seed S`` (the same seeds, in
the same order, on both sides: the pairs share their clouds). Per case (shape, noise, size) it
prints the median Chamfer-L1 before and after, their ratio, the geometric mean of the paired
ratios, how many seeds the after version won, and the median F-scores; then over every pair
the geometric mean and the cases worse than 2 % (issue 17: no case more than 2 % worse). One
seed's ratio swings by about the seed-to-seed spread printed last: a single seed cannot tell
2 % apart.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics


def load(path: str) -> dict:
    """{(shape, noise, n): row} of our method's rows in one `bench.quality` JSON file."""
    with open(path) as file:
        return {(r["shape"], r["noise"], r["n"]): r for r in json.load(file)
                if r["method"] == "ours"}


def compare(before: list[dict], after: list[dict]) -> tuple[list[dict], dict]:
    """Per-case rows and the summary of paired seeds (``before[i]`` and ``after[i]``)."""
    cases = sorted(set.intersection(*(set(run) for run in before + after)))
    rows, ratios = [], []
    for case in cases:
        old = [run[case]["chamfer_l1"] for run in before]
        new = [run[case]["chamfer_l1"] for run in after]
        paired = [b / a for a, b in zip(old, new, strict=True)]
        ratios += paired
        rows.append({
            "case": case, "before": statistics.median(old), "after": statistics.median(new),
            "paired": math.exp(statistics.fmean(map(math.log, paired))),
            "won": sum(r < 1 for r in paired), "seeds": len(paired),
            "f_before": statistics.median(run[case]["fscore"] for run in before),
            "f_after": statistics.median(run[case]["fscore"] for run in after)})
    spread = statistics.median(statistics.pstdev([math.log(run[case]["chamfer_l1"])
                                                  for run in before]) for case in cases)
    summary = {"pairs": len(ratios), "geomean": math.exp(statistics.fmean(map(math.log, ratios))),
               "won": sum(r < 1 for r in ratios),
               "worse_median": sum(r["after"] > 1.02 * r["before"] for r in rows),
               "worse_paired": sum(r["paired"] > 1.02 for r in rows), "spread": spread}
    return rows, summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", nargs="+", required=True)
    parser.add_argument("--after", nargs="+", required=True)
    args = parser.parse_args()
    if len(args.before) != len(args.after):
        parser.error("give as many --after files as --before files (one per seed)")
    rows, summary = compare([load(p) for p in args.before], [load(p) for p in args.after])
    print(f"{'case':24s} {'before':>9s} {'after':>9s} {'ratio':>6s} {'paired':>7s} {'won':>5s} "
          f"{'F before':>8s} {'F after':>8s}   (Chamfer-L1 medians over seeds)")
    for r in rows:
        shape, noise, n = r["case"]
        print(f"{shape:14s} {noise:<5g} {n:>5d} {r['before']:9.6f} {r['after']:9.6f} "
              f"{r['after'] / r['before']:6.3f} {r['paired']:7.3f} {r['won']:2d}/{r['seeds']:<2d} "
              f"{r['f_before']:8.4f} {r['f_after']:8.4f}")
    print(f"\n{summary['pairs']} pairs: geometric mean of the paired ratios "
          f"{summary['geomean']:.3f}, after better in {summary['won']}; cases over 2 % worse: "
          f"{summary['worse_median']} by the medians, {summary['worse_paired']} by the paired "
          f"ratios (target: none); seed-to-seed spread of log Chamfer before (median over "
          f"cases): {summary['spread']:.3f}")


if __name__ == "__main__":
    main()
