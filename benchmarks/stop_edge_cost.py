"""Issue 47: the default stop edge's cost against the DOE-plane edge (``stop_edge="doe"``), A/B in one process,
runs interleaved (A, B, A, B, …; medians), on the bundled ``hybrid_asphere`` (its blank 3 mm DOE at 1 µm, 0.7 mm
after the lens, 3 µm pixels): a single warm PSF (``psf_result`` of one field at one wavelength, ks 64; the lens and
its hybrid built and warmed once) and a PSF map (``psf_map``, N×N fields × the R, G, B channel centres, ks 64) per
PSF; also the Fresnel step alone (``edge_step="fresnel"``, the default before "adaptive"). Prints one JSON object
(and writes it with ``-o``) with ``single_ratio_vs_doe`` and ``map_ratio_vs_doe`` (median time of each edge / the
DOE-plane edge's).

``--clock cpu`` times the process's CPU time (``time.process_time``: robust on a shared machine with
``--threads 1``) instead of the wall clock. ``--ab TREE``: the same measurement for two source trees, the raywave
at ``TREE`` (e.g. a ``git worktree add --detach /tmp/base <commit>``) and the one this script imports, in
alternating subprocesses (old, new, old, new, …: ``--repeat`` rounds of one repetition each), reporting each tree's
ratios (medians over the rounds) and the new tree's time over the old one's per edge.

    PYTHONPATH=. python benchmarks/stop_edge_cost.py [--grid 3] [--repeat 3] [--threads 2] [--field 12.25]
        [--edges default,doe] [--clock cpu] [--singles 5] [--ab /tmp/base] [-o F]
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import warnings

EDGES = {"default": {}, "fresnel": {"edge_step": "fresnel"}, "doe": {"stop_edge": "doe"}}
WAVELENGTHS = (0.66, 0.53, 0.47)


def _parser():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, default=3, help="N: the map's N×N fields (0: no map)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--singles", type=int, default=3, help="single-PSF timings per edge per repetition (median)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--field", type=float, default=12.25, help="field (deg) of the single PSF")
    ap.add_argument("--edges", default="default,fresnel,doe", help="comma-separated, of " + ", ".join(EDGES))
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall")
    ap.add_argument("--ab", default=None, help="source tree of the old code (A/B in alternating subprocesses)")
    ap.add_argument("--parallel", action="store_true", help="--ab: each round's two subprocesses at once (a machine "
                    "shared with other work: both see the same load; with --clock cpu)")
    ap.add_argument("--inner", type=int, default=1, help="--ab: repetitions inside each subprocess (the last one's "
                    "ratios are the warm ones: its maps follow a map of the same size)")
    ap.add_argument("--psfs-out", default=None, help="save each edge's last map PSFs (torch.save of a dict)")
    ap.add_argument("-o", "--output")
    return ap


def measure(a) -> dict:
    """One process's interleaved measurement of the edges ``a.edges`` (the raywave on ``sys.path``)."""
    import torch

    from raywave.assembly.build import load_hybrid
    from raywave.imaging import psf_map
    from raywave.lens.build import bundled_lens_path

    clock = time.process_time if a.clock == "cpu" else time.perf_counter

    def timed(fn) -> float:
        t = clock()
        fn()
        return clock() - t

    torch.set_num_threads(a.threads)
    torch.set_grad_enabled(False)
    warnings.simplefilter("ignore")
    edges = a.edges.split(",")
    hls = {k: load_hybrid(bundled_lens_path("hybrid_asphere"), **EDGES[k]) for k in edges}
    for hl in hls.values():  # warm: the lens's caches, the transfer functions, the thread pool
        hl.psf_result((0.0, a.field), 0.53, ks=64)
        if a.grid:
            psf_map(hl, (2, 2), wavelengths=WAVELENGTHS, ks=64, progress=False)
    single = {k: [] for k in hls}
    maps = {k: [] for k in hls}
    last = {}
    for _ in range(a.repeat):
        for _ in range(a.singles):
            for k, hl in hls.items():
                single[k].append(timed(lambda: hl.psf_result((0.0, a.field), 0.53, ks=64)))
        if a.grid:
            n = a.grid * a.grid * len(WAVELENGTHS)
            for k, hl in hls.items():
                maps[k].append(timed(lambda: last.__setitem__(k, psf_map(hl, (a.grid, a.grid), wavelengths=WAVELENGTHS,
                                                                         ks=64, progress=False))) / n)
    if a.psfs_out and last:
        torch.save({k: m.psf.detach().cpu() for k, m in last.items()}, a.psfs_out)
    med = {k: statistics.median(v) for k, v in single.items()}
    out = dict(case=f"hybrid_asphere, single PSF at {a.field} deg 0.53 um ks 64; map {a.grid}x{a.grid}x3 ks 64",
               threads=a.threads, clock=a.clock, repeat=a.repeat, single_s=single, map_s_per_psf=maps,
               single_ratio_vs_doe={k: med[k] / med["doe"] for k in med} if "doe" in med else None,
               steps={k: hl.edge_step for k, hl in hls.items()})
    if a.grid:
        mmed = {k: statistics.median(v) for k, v in maps.items()}
        out["map_ratio_vs_doe"] = {k: mmed[k] / mmed["doe"] for k in mmed} if "doe" in mmed else None
    return out


def ab(a) -> dict:
    """``--ab``: subprocesses of this script on the old tree and on this one, alternating (or, with ``--parallel``,
    each round's two at once), ``--inner`` repetitions each."""
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    import raywave

    new_tree = os.path.dirname(os.path.dirname(os.path.abspath(raywave.__file__)))
    trees = {"old": os.path.abspath(a.ab), "new": new_tree}
    args = ["--grid", str(a.grid), "--repeat", str(a.inner), "--singles", str(a.singles), "--threads", str(a.threads),
            "--field", str(a.field), "--edges", a.edges, "--clock", a.clock]
    runs = {k: [] for k in trees}
    saved = {k: os.path.join(tempfile.mkdtemp(prefix="stop_edge_cost_"), "psfs.pt") for k in trees}
    for r in range(a.repeat):
        procs = {}
        for name, tree in trees.items():
            env = dict(os.environ, PYTHONPATH=tree, OMP_NUM_THREADS=str(a.threads))
            extra = ["--psfs-out", saved[name]] if r == 0 and a.grid else []
            procs[name] = subprocess.Popen([sys.executable, os.path.abspath(__file__)] + args + extra, env=env,
                                           cwd=here, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            if not a.parallel:
                procs[name].wait()
        for name, proc in procs.items():
            stdout, stderr = proc.communicate()
            if proc.returncode:
                raise RuntimeError(f"{name} run failed:\n{stderr[-2000:]}")
            runs[name].append(json.loads(stdout.strip().splitlines()[-1]))
            print(f"round {r} {name}: single {runs[name][-1]['single_ratio_vs_doe']} map "
                  f"{runs[name][-1].get('map_ratio_vs_doe')}", file=sys.stderr, flush=True)
    edges = a.edges.split(",")
    out = dict(case=runs["new"][0]["case"], threads=a.threads, clock=a.clock, rounds=a.repeat, inner=a.inner,
               parallel=a.parallel, trees=trees, runs=runs)
    for what, key in (("single", "single_s"), ("map", "map_s_per_psf")):
        if what == "map" and not a.grid:
            continue
        per = {name: {k: [statistics.median(run[key][k]) for run in rs] for k in edges} for name, rs in runs.items()}
        out[f"{what}_s_median"] = {name: {k: statistics.median(v) for k, v in p.items()} for name, p in per.items()}
        if "doe" in edges:  # each round's ratio (its processes' own interleaved runs), then the median
            out[f"{what}_ratio_vs_doe"] = {name: {k: statistics.median([x / y for x, y in zip(p[k], p["doe"])])
                                                  for k in edges} for name, p in per.items()}
        out[f"{what}_new_over_old"] = {k: statistics.median([x / y for x, y in zip(per["new"][k], per["old"][k])])
                                       for k in edges}
    if a.inner > 1:  # the last repetition inside each subprocess (its maps follow maps of the same size)
        for what, key in (("single", "single_s"), ("map", "map_s_per_psf")):
            if (what == "map" and not a.grid) or "doe" not in edges:
                continue
            step = a.singles if what == "single" else 1
            last = {name: [{k: statistics.median(run[key][k][-step:]) for k in edges} for run in rs]
                    for name, rs in runs.items()}
            out[f"{what}_ratio_vs_doe_last_inner"] = {
                name: {k: statistics.median([v[k] / v["doe"] for v in ls]) for k in edges} for name, ls in last.items()}
            out[f"{what}_new_over_old_last_inner"] = {
                k: statistics.median([x[k] / y[k] for x, y in zip(last["new"], last["old"])]) for k in edges}
    if a.grid:  # the new tree's map PSFs against the old one's (first round)
        import torch

        old, new = (torch.load(saved[k]) for k in ("old", "new"))
        out["map_psfs_new_vs_old"] = {
            k: dict(max_abs=float((new[k] - old[k]).abs().max()),
                    max_rel_l1=float(((new[k] - old[k]).abs().sum((-2, -1))
                                      / old[k].abs().sum((-2, -1)).clamp_min(1e-300)).max()),
                    psfs=int(old[k][..., 0, 0].numel())) for k in edges}
    return out


def main(argv=None):
    a = _parser().parse_args(argv)
    out = ab(a) if a.ab else measure(a)
    print(json.dumps(out))
    if a.output:
        with open(a.output, "w") as f:
            json.dump(out, f, indent=1)
    return out


if __name__ == "__main__":
    main()
