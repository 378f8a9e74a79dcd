import os, sys, torch, math
sys.path.insert(0, "benchmarks"); sys.path.insert(0, ".")
torch.set_grad_enabled(False)
import stop_edge_references as S
from raywave.hybrid.coherent import exit_pupil as X
from raywave.hybrid.coherent.sphere_chart import sample_bicubic
case = sys.argv[1]
b = torch.load(os.environ.get("RUNS", "runs") + "/planar_same.pt", weights_only=False); si = b["scin"]
fx, fy, fz = si["sphere"]; z_from = si["planes"][0]
saved = {}
def grab(fin):
    env, g = fin.envelope, fin.grid
    (ny, nx), (x0, y0), p = g.shape, g.origin, g.pitch[0]
    print("plain construction", g.shape, p, g.origin, fin.carrier, flush=True)
    k = 2*math.pi*fin.n/(fin.wavelength*1e-3)
    xs = x0 + torch.arange(nx, dtype=torch.float64)*p; ys = y0 + torch.arange(ny, dtype=torch.float64)*p
    r1 = fz - z_from
    # true field = env*exp(ik(car.x)); sphere S = exp(-ik (r - r1)); envelope rel sphere = env*exp(ik car.x)/S
    A = torch.empty_like(env)
    for i in range(0, ny, 512):
        yy = ys[i:i+512, None]
        rr = torch.sqrt((xs[None]-fx)**2 + (yy-fy)**2 + r1*r1)
        A[i:i+512] = env[i:i+512] * torch.polar(torch.ones_like(rr), k*(fin.carrier[0]*xs[None] + fin.carrier[1]*yy + (rr - r1)))
    F_ = int(os.environ.get("FACT", "1")); (sy, sx), (sx0, sy0), q = si["shape"], si["origin"], si["pitch"][0]; sy, sx, q = sy*F_, sx*F_, q/F_
    qx = sx0 + torch.arange(sx, dtype=torch.float64)*q; qy = sy0 + torch.arange(sy, dtype=torch.float64)*q
    As = sample_bicubic(A, (x0, y0), p, qx[None].expand(sy, sx), qy[:, None].expand(sy, sx))
    saved["A"] = As; saved["grid"] = ((sx0, sy0), q, (sy, sx))
orig_pw, orig_cp = X.propagate_window, X._coarse_propagate
def pw(fin, grid, dz, **k):
    if "A" not in saved: grab(fin)
    return orig_pw(fin, grid, dz, **k)
def cp(fin, *a, **k):
    if "A" not in saved: grab(fin)
    return orig_cp(fin, *a, **k)
X.propagate_window, X._coarse_propagate = pw, cp
eng, geo = S.engine_psfs(case, 32, ["default"])
torch.save(saved, f"{os.environ.get('RUNS', 'runs')}/planar_plainA{os.environ.get('FACT', '1')}.pt")
