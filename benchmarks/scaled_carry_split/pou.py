import torch, math
def good(n):
    m = n
    while True:
        r = m
        for p_ in (2, 3, 5):
            while r % p_ == 0: r //= p_
        if r == 1: return m
        m += 1
def hats(t, nodes):
    """(P, len(t)) 1D hat partition of unity on sorted nodes (flat beyond the ends)."""
    P = len(nodes)
    if P == 1: return torch.ones(1, t.numel(), dtype=t.dtype)
    w = []
    for j in range(P):
        y = torch.zeros_like(t)
        if j > 0:
            a, b = nodes[j-1], nodes[j]; m = (t >= a) & (t <= b); y[m] = (t[m]-a)/(b-a)
        else: y[t <= nodes[0]] = 1.0
        if j < P-1:
            a, b = nodes[j], nodes[j+1]; m = (t >= a) & (t <= b); y[m] = (b - t[m])/(b-a)
        else: y[t >= nodes[-1]] = 1.0
        w.append(y)
    return torch.stack(w)
def metric(x, y, sphere, r1):
    dx, dy = x - sphere[0], y - sphere[1]
    r = math.sqrt(dx*dx + dy*dy + r1*r1); ux, uy, g = dx/r, dy/r, abs(r1)/r
    return torch.tensor([[g*(1-ux*ux), -g*ux*uy], [-g*ux*uy, g*(1-uy*uy)]], dtype=torch.float64)
def pou_carry(field, out, sphere, planes, carrier, P=4, thresh=1e-3, mode='in'):
    fx, fy, fz = sphere; z_from, z_doe = planes
    r1, r2 = fz - z_from, fz - z_doe; mag = r2/r1; L = (z_doe - z_from)*r1/r2
    env = field.envelope; (ny, nx), (x0, y0), q = field.grid.shape, field.grid.origin, field.grid.pitch[0]
    ox, oy = out.origin
    f = max(1, int(round(out.pitch[0]/mag/q)))
    sx0, sy0 = fx + (ox - fx)/mag, fy + (oy - fy)/mag
    sny, snx = f*(out.shape[0]-1)+1, f*(out.shape[1]-1)+1
    # offsets (in samples) of src relative to input
    ix, iy = round((sx0 - x0)/q), round((sy0 - y0)/q)
    lo_x, lo_y = min(0, ix), min(0, iy)
    hi_x, hi_y = max(nx, ix+snx), max(ny, iy+sny)
    Nx, Ny = good(hi_x - lo_x + nx), good(hi_y - lo_y + ny)
    lam = field.wavelength*1e-3/field.n
    fxs = torch.fft.fftfreq(Nx, d=q, dtype=torch.float64); fys = torch.fft.fftfreq(Ny, d=q, dtype=torch.float64)
    kz = torch.sqrt((1/lam**2 - fxs[None]**2 - fys[:, None]**2).clamp_min(0))
    base = torch.polar(torch.ones_like(kz), 2*math.pi*L*kz) * ((fxs[None]**2 + fys[:, None]**2) < 1/lam**2)
    xs = x0 + torch.arange(nx, dtype=torch.float64)*q; ys = y0 + torch.arange(ny, dtype=torch.float64)*q
    w = env.abs()**2
    # nodes over the beam's extent
    mx_ = w.sum(0) > thresh*w.sum(0).max(); my_ = w.sum(1) > thresh*w.sum(1).max()
    bx = (float(xs[mx_].min()), float(xs[mx_].max())); by = (float(ys[my_].min()), float(ys[my_].max()))
    nxs = [bx[0] + (bx[1]-bx[0])*j/(P-1) for j in range(P)] if P > 1 else [0.5*(bx[0]+bx[1])]
    nys = [by[0] + (by[1]-by[0])*j/(P-1) for j in range(P)] if P > 1 else [0.5*(by[0]+by[1])]
    hx, hy = hats(xs, nxs), hats(ys, nys)
    acc = None; spec = None
    xg = x0 + (torch.arange(Nx, dtype=torch.float64) + lo_x)*q; yg = y0 + (torch.arange(Ny, dtype=torch.float64) + lo_y)*q
    hxo, hyo = hats(xg, nxs), hats(yg, nys)
    FX, FY = fxs[None], fys[:, None]
    for a in range(len(nys)):
        for b in range(len(nxs)):
            G = metric(nxs[b], nys[a], sphere, r1)
            D = torch.linalg.inv(G) - torch.eye(2, dtype=torch.float64)
            T = base * torch.polar(torch.ones_like(kz), -math.pi*lam*L*(D[0,0]*FX**2 + 2*D[0,1]*FX*FY + D[1,1]*FY**2))
            if mode == 'in':
                piece = env * (hy[a][:, None]*hx[b][None, :]).to(env.dtype)
                buf = torch.zeros(Ny, Nx, dtype=env.dtype)
                buf[-lo_y:-lo_y+ny, -lo_x:-lo_x+nx] = piece
                S = torch.fft.fft2(buf) * T
                acc = S if acc is None else acc + S
            else:
                if spec is None:
                    buf = torch.zeros(Ny, Nx, dtype=env.dtype); buf[-lo_y:-lo_y+ny, -lo_x:-lo_x+nx] = env
                    spec = torch.fft.fft2(buf); del buf
                S = torch.fft.ifft2(spec * T)
                wo = (hyo[a][:, None]*hxo[b][None, :]).to(env.dtype)
                acc = S*wo if acc is None else acc + S*wo
            del S, T
    res = torch.fft.ifft2(acc) if mode == 'in' else acc
    a_ = res[iy-lo_y:iy-lo_y+sny:f, ix-lo_x:ix-lo_x+snx:f]
    k = 2*math.pi*field.n/(field.wavelength*1e-3)
    xo = ox + torch.arange(out.shape[1], dtype=torch.float64)*out.pitch[0]
    yo = oy + torch.arange(out.shape[0], dtype=torch.float64)*out.pitch[1]
    rr = torch.sqrt((xo[None]-fx)**2 + (yo[:, None]-fy)**2 + r2*r2)
    phase = -k*((rr - abs(r2)) + carrier[0]*xo[None] + carrier[1]*yo[:, None])
    return a_ * torch.polar(torch.full_like(rr, 1.0/mag), phase).to(a_.dtype)
