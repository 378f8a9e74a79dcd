"""How much a numeric switch moves a demo config's evaluation PSF map: the map (eval_grid, its wavelengths, depths,
eval_ks) of the config's hybrid (zero-phase learned DOE, as training starts) with raywave.hybrid.coherent.accurate.
RIM_FOURIER True vs False, same process. Prints JSON."""
import json, sys, time, warnings
import torch
import raywave.hybrid.coherent.accurate as acc
from raywave.training.config import load_config
from raywave.training.trainer import build_hybrid
from raywave.imaging.psfmap import field_grid

cfg = load_config(sys.argv[1])
hl = build_hybrid(cfg.lens)
o = cfg.optics
wl = o.wavelengths
wls = [w for c in ("R", "G", "B") for w in wl[c]] if isinstance(wl, dict) else list(wl)
depths = list(getattr(o, "depths", None) or [None])
ks = int(o.eval_ks or o.ks)
rows = []
for d in depths:
    dd = None if d is None or d >= 1e9 else float(d)
    f = field_grid(hl, tuple(o.eval_grid), depth=dd).reshape(-1, 2)
    out = {}
    for flag in (True, False):
        acc.RIM_FOURIER = flag
        t = time.time()
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ps = []
            for s in range(0, f.shape[0], 5):
                ps.append(hl.psf_result(f[s:s + 5], wls, ks=ks, depth=dd).psf)
        out[flag] = (torch.cat(ps), time.time() - t)
    a, b = out[True][0], out[False][0]
    rel = ((a - b).abs().sum((-1, -2)) / b.abs().sum((-1, -2)))
    rows.append({"depth": d, "n_psfs": int(rel.numel()), "max_rel_l1": float(rel.max()),
                 "median_rel_l1": float(rel.median()), "n_over_1e-4": int((rel > 1e-4).sum())})
    print(json.dumps(rows[-1]), flush=True)
print(json.dumps({"config": sys.argv[1], "ks": ks, "wavelengths": wls, "rows": rows}))
