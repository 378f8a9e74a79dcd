from disc import *
from pou import pou_carry
import functools
amp = lambda x, y: torch.polar(torch.ones((), dtype=torch.float64), 105.0*(x*x - 0.5*y*y + 0.3*x*y))
for tilt in (0.0, 10.6):
  for name, fn in [("pou5out", functools.partial(pou_carry, P=5, mode='out')), ("pou3out", functools.partial(pou_carry, P=3, mode='out'))]:
    r, d = case(edge=0.01, a=0.54, fz=3.0, z2=1.8, tilt=tilt, pitch=0.6e-3, carry=fn, amp=amp)
    print(tilt, name, r, "psfL1 96", psf_l1(*d, crop_px=96), "64", psf_l1(*d, crop_px=64), "32", psf_l1(*d, crop_px=32), flush=True)
