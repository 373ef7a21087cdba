"""Summarise a compile log of ``scripts/compile_log/sitecustomize.py``: compile seconds by
program, by test module and by size, and the programs compiled more than once (the same text and
options in several tests or processes: what a shared persistent cache could save).

    .venv/bin/python scripts/compile_log/summary.py /tmp/complog
"""

import argparse
import collections
import pathlib


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("folder", type=pathlib.Path, help="THREEPT_COMPILE_LOG of the run")
    p.add_argument("--top", type=int, default=15, help="rows per table")
    args = p.parse_args()
    rows = []
    for f in sorted(args.folder.glob("*.tsv")):
        for i, line in enumerate(f.read_text().splitlines(), 1):
            fields = line.split("\t")
            if len(fields) != 6:
                raise SystemExit(f"{f}:{i}: not a line of scripts/compile_log/sitecustomize.py "
                                 f"(6 tab-separated fields, got {len(fields)}); point at the "
                                 "folder of THREEPT_COMPILE_LOG")
            start, seconds, text, options, name, test = fields
            rows.append((float(seconds), text, options, name, test.split("::")[0], f.stem))
    if not rows:
        raise SystemExit(f"no compile log in {args.folder} (*.tsv)")
    total = sum(r[0] for r in rows)
    print(f"{total:.1f} s of XLA compilation in {len(rows)} compilations")
    for title, key in (("by program", lambda r: r[3]), ("by test module", lambda r: r[4])):
        seconds, count = collections.Counter(), collections.Counter()
        for r in rows:
            seconds[key(r)] += r[0]
            count[key(r)] += 1
        print(f"\n{title}: seconds, compilations")
        for k, s in seconds.most_common(args.top):
            print(f"{s:8.1f} {count[k]:5d}  {k}")
    print("\nby size: seconds, compilations")
    for lo, hi in ((0, 0.2), (0.2, 1), (1, 5), (5, float("inf"))):
        sel = [r[0] for r in rows if lo <= r[0] < hi]
        print(f"  {lo:g}-{hi:g} s: {sum(sel):8.1f} {len(sel):5d}")
    groups = collections.defaultdict(list)
    for r in rows:
        groups[r[1], r[2]].append(r)
    repeated = sorted(((sum(r[0] for r in g[1:]), g) for g in groups.values() if len(g) > 1),
                      key=lambda x: -x[0])
    print(f"\nrepeated programs: {sum(s for s, _ in repeated):.1f} s after their first "
          "compilation")
    for s, g in repeated[:args.top]:
        where = sorted({f"{r[4]} (pid {r[5]})" for r in g})
        print(f"{s:8.1f} {len(g):3d}x {g[0][3]}: {', '.join(where)}")


if __name__ == "__main__":
    main()
