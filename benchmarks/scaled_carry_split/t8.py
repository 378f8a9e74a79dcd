from disc import *
from pou import pou_carry
import functools
amp = lambda x, y: torch.polar(torch.ones((), dtype=torch.float64), 105.0*(x*x - 0.5*y*y + 0.3*x*y))
for name, fn in [("main", None), ("pou3", functools.partial(pou_carry, P=3)), ("pou5", functools.partial(pou_carry, P=5))]:
    r, d = case(edge=0.01, a=0.54, fz=3.0, z2=1.8, tilt=0.0, pitch=0.6e-3, carry=fn, amp=amp)
    print(name, r, "psfL1 96", psf_l1(*d, crop_px=96), "64", psf_l1(*d, crop_px=64), "32", psf_l1(*d, crop_px=32), flush=True)
