from disc import *
from pou import pou_carry
import functools
for c in (50.0, 105.0):
  amp = lambda x, y, c=c: torch.polar(torch.ones((), dtype=torch.float64), c*(x*x - 0.5*y*y + 0.3*x*y))
  for tilt in (10.6,):
    for name, fn in [("main", None), ("pou3", functools.partial(pou_carry, P=3))]:
      r, d = case(edge=0.01, a=0.54, fz=3.0, z2=1.8, tilt=tilt, pitch=0.6e-3, carry=fn, amp=amp)
      print(c, tilt, name, r, "psfL1", psf_l1(*d, crop_px=96), flush=True)
