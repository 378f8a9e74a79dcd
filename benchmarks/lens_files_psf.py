"""What a newcomer meets running ``raywave psf`` on real camera lenses: for a seeded random sample of the
OpticExplorer database's .zmx files (../shared/data/opticsdatabase, MIT), the default PSF (a blank DOE at the default
plane, the default edge, ks 32, the primary wavelength) on axis and at 0.7 of the largest field, each in a fresh
process per tree. Prints one JSON row per file, field and tree: the time (s, wall, one thread), the DOE's
``distance_rule`` and plane, its grid, the warning categories (with their first words) or the error, and for two
trees the PSFs' relative L1 difference.

    d=/tmp/optics && mkdir -p $d && tar xzf ../shared/data/opticsdatabase/optics.tar.gz -C $d
    python benchmarks/lens_files_psf.py $d/Optics/Photography [--n 8] [--seed 1] [--trees A B] [--timeout 300]
        [--clip-apertures off|on|both] [-o benchmarks/results/lens_files_psf.json]

``--trees``: source trees whose ``raywave`` to run (default: this one); each file and field runs in every tree in
turn (A, B, A, B…), so the trees share the machine's load.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import emit_row  # noqa: E402

#: the child process: one default PSF, its record printed as one JSON line, the PSF saved to argv[4]
CHILD = r"""
import json, sys, time, warnings
import numpy as np, torch
torch.set_num_threads(1)
from raywave.cli.psf_commands import compute_psf
from raywave.lens.build import load_lens
path, frac, out, clip = sys.argv[1], float(sys.argv[2]), sys.argv[3], sys.argv[4] == "1"
row = {}
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    try:
        lens = load_lens(path)
        fmax = max(abs(float(f)) for f in lens.fields)
        t = time.perf_counter()
        res = compute_psf(path, field=(0.0, frac * fmax), ks=32, **({"clip_apertures": True} if clip else {}))
        row["s"] = round(time.perf_counter() - t, 2)
        info = res["hybrid"].doe_info
        row.update(field=round(frac * fmax, 4), rule=info.get("distance_rule"), distance=info.get("distance"),
                   shape=info.get("shape"), pitch_um=info["pitch"] * 1e3)
        np.save(out, np.asarray(res["psf"]))
    except Exception as err:  # a refusal is a result here
        row["error"] = f"{type(err).__name__}: {str(err)[:160]}"
names = sorted({f"{w.category.__name__}: {' '.join(str(w.message).split()[:8])[:90]}" for w in caught
                if w.category.__name__ not in ("DeprecationWarning", "LensFileWarning", "FieldSolveWarning")})
row["warnings"] = names
print(json.dumps(row))
"""


def run_child(tree: str, path: Path, frac: float, psf_out: str, timeout: float, clip: bool = False) -> dict:
    """One default PSF of ``path`` at ``frac`` of its largest field with ``tree``'s raywave (a fresh process);
    ``clip``: with ``clip_apertures=True`` (the surfaces' semi-diameters vignette)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(Path(tree).resolve()))
    try:
        done = subprocess.run([sys.executable, "-c", CHILD, str(path), str(frac), psf_out, "1" if clip else "0"],
                              env=env,
                              capture_output=True, text=True, timeout=timeout, cwd=tempfile.gettempdir())
    except subprocess.TimeoutExpired:
        return {"error": f"timeout {timeout:g} s"}
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("{")]
    return json.loads(lines[-1]) if lines else {"error": f"rc {done.returncode}: {done.stderr.strip()[-200:]}"}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", help="a folder of .zmx files (searched recursively)")
    ap.add_argument("--n", type=int, default=8)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--trees", nargs="*", default=[str(Path(__file__).resolve().parents[1])])
    ap.add_argument("--fracs", type=float, nargs="*", default=[0.0, 0.7])
    ap.add_argument("--timeout", type=float, default=300.0)
    ap.add_argument("--clip-apertures", choices=("off", "on", "both"), default="off",
                    help="load with clip_apertures (the semi-diameters vignette); both: each PSF plainly and "
                         "clipped, the clipped one compared with the plain one (rel_l1_vs_plain)")
    ap.add_argument("-o", "--output")
    args = ap.parse_args(argv)
    files = sorted(Path(args.root).rglob("*.zmx"))
    pick = random.Random(args.seed).sample(files, min(args.n, len(files)))
    rows: list = []
    with tempfile.TemporaryDirectory() as tmp:
        for path in pick:
            for frac in args.fracs:
                psfs = []
                for k, tree in enumerate(args.trees):
                    plain = None
                    for clip in {"off": [False], "on": [True], "both": [False, True]}[args.clip_apertures]:
                        out = os.path.join(tmp, f"psf{k}{'c' if clip else ''}.npy")
                        row = run_child(tree, path, frac, out, args.timeout, clip)
                        row.update(file=str(path.relative_to(args.root)), frac=frac, tree=tree, clip_apertures=clip)
                        if not clip or args.clip_apertures == "on":
                            psfs.append(out if "s" in row else None)
                            if k and psfs[0] and psfs[k]:
                                a, b = np.load(psfs[0]), np.load(psfs[k])
                                row["rel_l1_vs_first_tree"] = float(abs(a - b).sum() / abs(a).sum())
                        if not clip:
                            plain = out if "s" in row else None
                        elif plain and "s" in row:
                            a, b = np.load(plain), np.load(out)
                            row["rel_l1_vs_plain"] = float(abs(a - b).sum() / abs(a).sum())
                        emit_row(rows, row, args.output)


if __name__ == "__main__":
    main()
