"""Issue 44: how many real lens files raywave reads. Loads every .zmx / .seq under ROOT with
``raywave.load_lens(path).paraxial()`` and prints, as JSON, the count read with finite paraxial data, the
refusals grouped by cause (the error message with the path, numbers, quoted names and surface numbers
normalised) with one example file and message per cause, and the warnings grouped the same way.

    d=/tmp/optics && mkdir -p $d && tar xzf ../shared/data/opticsdatabase/optics.tar.gz -C $d
    PYTHONPATH=. python benchmarks/lens_files.py $d/Optics [-o benchmarks/results/lens_files.json]
        [--map-unknown-glass]  # diagnostic only: an unknown glass becomes a model glass nd 1.5, vd 60, to
                               # see what else a file would fail on (counted separately)
        [--optiland]           # also compare each file read with Optiland 0.6.3 where Optiland reads it
                               # faithfully (benchmarks/_optiland_compare.py): count and worst difference
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import time
import warnings
from collections import Counter, defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import emit_json  # noqa: E402

_NUM = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_QUOTED = re.compile(r"'[^']*'|\"[^\"]*\"")


#: Files listed per reason Optiland is not compared (all of a rare reason, such as a non-finite value).
NOT_COMPARED_LISTED = 12


def cause(message: str, path: str) -> str:
    """The message of an error or warning with the file, numbers and quoted names normalised (its cause)."""
    text = str(message).split("\n")[0].replace(path, "<file>")
    text = re.sub(r"^<file>(:\d+)?(:\d+)?: ", "", text)
    text = text.replace(path, "<file>")
    text = _QUOTED.sub("'X'", text)
    text = _NUM.sub("N", text)
    return text[:200]


def _is_unknown_glass(err: Exception) -> bool:
    from raywave.materials.catalog import GlassNotFoundError

    return isinstance(err, GlassNotFoundError)


def load_one(path: Path, map_glass: bool):
    """(status, message, warnings, lens): status "read", or the exception type; warnings as caught."""
    import raywave

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            lens = raywave.load_lens(path)
            p = lens.paraxial()
            vals = [p.efl, p.bfl, p.epd, p.ep_z, p.xp_z, p.xpd]
            if not all(math.isfinite(float(v)) for v in vals):
                return "nonfinite", f"non-finite paraxial data {vals}", caught, None
            return "read", "", caught, lens
        except Exception as err:  # noqa: BLE001 - a benchmark counts every refusal by its cause
            kind = "unknown_glass" if _is_unknown_glass(err) else type(err).__name__
            return kind, str(err), caught, None


def _map_unknown_glasses():
    """Diagnostic: an unknown glass name becomes a model glass (nd 1.5, vd 60) instead of an error."""
    import raywave.lens.build as build
    from raywave.materials.catalog import GlassNotFoundError

    original = build.get_material

    def tolerant(name, catalogs=None):
        try:
            return original(name, catalogs=catalogs)
        except GlassNotFoundError:
            return original({"model": {"nd": 1.5, "vd": 60.0}})

    build.get_material = tolerant


def run(root: str, map_unknown_glass: bool = False, optiland: bool = False, examples: int = 2,
        shard: tuple[int, int] = (0, 1)) -> dict:
    """The report (a dict) on every .zmx / .seq under ``root`` (``shard`` (i, n): every n-th file from the i-th,
    for runs in parallel merged with :func:`merge`): see the module docstring."""
    if map_unknown_glass:
        _map_unknown_glasses()
    files = sorted(p for p in Path(root).rglob("*") if p.suffix.lower() in (".zmx", ".seq"))[shard[0]::shard[1]]
    t0 = time.perf_counter()
    status = Counter()
    causes: dict[str, list] = defaultdict(list)
    warns: Counter = Counter()
    warn_files: dict[str, set] = defaultdict(set)
    worst = {}
    compared, skipped = 0, Counter()
    skipped_files: dict[str, list] = defaultdict(list)  # reason -> [(file, message)]: which files, and why
    for i, f in enumerate(files):
        st, msg, caught, lens = load_one(f, map_unknown_glass)
        status[st] += 1
        if i % 100 == 0:
            print(f"{i}/{len(files)} read {status['read']}", file=sys.stderr, flush=True)
        if optiland and lens is not None:
            from _optiland_compare import NotFaithful, compare

            try:
                diffs = compare(str(f), lens)
                compared += 1
                for q, v in diffs.items():
                    if v >= worst.get(q, (-1.0, ""))[0]:
                        worst[q] = (v, str(f.relative_to(root)))
            except NotFaithful as why:
                skipped[cause(str(why), str(f))] += 1
                skipped_files[cause(str(why), str(f))].append((str(f.relative_to(root)), str(why)))
            except Exception as err:  # noqa: BLE001 - an Optiland failure is a reason not to compare
                skipped[f"Optiland fails: {type(err).__name__}: {cause(str(err), str(f))[:100]}"] += 1
        if st != "read":
            causes[f"{st}: {cause(msg, str(f))}"].append((str(f.relative_to(root)), msg.replace(str(f), "<file>")))
        for w in caught:
            key = f"{w.category.__name__}: {cause(str(w.message), str(f))}"
            warns[key] += 1
            warn_files[key].add(f.name)
    refused = sorted(causes.items(), key=lambda kv: -len(kv[1]))
    report = {
        "root": str(root),
        "files": len(files),
        "read": status["read"],
        "read_fraction": round(status["read"] / max(1, len(files)), 4),
        "refused": len(files) - status["read"],
        "refused_unknown_glass": status["unknown_glass"],
        "map_unknown_glass": map_unknown_glass,
        "refusals_by_cause": [{"cause": c, "count": len(v), "examples": [{"file": f, "message": m[:300]}
                                                                        for f, m in v[:examples]]}
                              for c, v in refused],
        "warnings_by_cause": [{"cause": c, "count": n, "files": len(warn_files[c])} for c, n in warns.most_common()],
        "seconds": round(time.perf_counter() - t0, 1),
    }
    if optiland:
        report["optiland"] = {"compared": compared,
                              "worst_relative_difference": {q: {"value": v, "file": f} for q, (v, f) in worst.items()},
                              "not_compared_by_reason": dict(skipped.most_common()),
                              "not_compared_files": {r: [{"file": f, "why": m[:300]} for f, m in v[:NOT_COMPARED_LISTED]]
                                                     for r, v in skipped_files.items()}}
    return report


def merge(reports: list[dict], examples: int = 2) -> dict:
    """One report of the shards ``reports`` (the same root, disjoint files)."""
    out = dict(reports[0])
    for k in ("files", "read", "refused", "refused_unknown_glass"):
        out[k] = sum(r[k] for r in reports)
    out["read_fraction"] = round(out["read"] / max(1, out["files"]), 4)
    out["seconds"] = max(r["seconds"] for r in reports)
    for key, item in (("refusals_by_cause", "examples"), ("warnings_by_cause", None)):
        groups: dict = {}
        for r in reports:
            for g in r[key]:
                acc = groups.setdefault(g["cause"], dict(g, count=0, **({item: []} if item else {"files": 0})))
                acc["count"] += g["count"]
                if item:
                    acc[item] = (acc[item] + g[item])[:examples]
                else:
                    acc["files"] += g["files"]
        out[key] = sorted(groups.values(), key=lambda g: -g["count"])
    if all("optiland" in r for r in reports):
        worst = {}
        for r in reports:
            for q, v in r["optiland"]["worst_relative_difference"].items():
                if v["value"] >= worst.get(q, {"value": -1.0})["value"]:
                    worst[q] = v
        reasons: Counter = Counter()
        for r in reports:
            reasons.update(r["optiland"]["not_compared_by_reason"])
        listed: dict = {}
        for r in reports:
            for reason, v in r["optiland"].get("not_compared_files", {}).items():
                listed[reason] = (listed.get(reason, []) + v)[:NOT_COMPARED_LISTED]
        out["optiland"] = {"compared": sum(r["optiland"]["compared"] for r in reports),
                           "worst_relative_difference": worst, "not_compared_by_reason": dict(reasons.most_common()),
                           "not_compared_files": listed}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("root", help="folder searched recursively for .zmx and .seq files")
    ap.add_argument("-o", "--output", help="also write the JSON here")
    ap.add_argument("--map-unknown-glass", action="store_true",
                    help="diagnostic: map unknown glasses to a model glass to see what else fails")
    ap.add_argument("--examples", type=int, default=2, help="example files per cause")
    ap.add_argument("--optiland", action="store_true", help="compare with Optiland where it reads a file faithfully")
    ap.add_argument("--shard", default="0/1", help="i/n: every n-th file from the i-th (parallel runs)")
    ap.add_argument("--merge", nargs="+", default=None, help="merge these shard reports (JSON files) instead")
    args = ap.parse_args(argv)
    if args.merge:
        import json

        emit_json(merge([json.load(open(p)) for p in args.merge], args.examples), args.output)
        return
    i, n = (int(v) for v in args.shard.split("/"))
    emit_json(run(args.root, args.map_unknown_glass, args.optiland, args.examples, (i, n)), args.output)


if __name__ == "__main__":
    main()
