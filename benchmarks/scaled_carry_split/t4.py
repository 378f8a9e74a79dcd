from disc import *
from pou import pou_carry
import functools
for tilt in (10.6, 30):
  for name, fn in [("main", None), ("pou1", functools.partial(pou_carry, P=1)), ("pou3", functools.partial(pou_carry, P=3))]:
    r, d = case(edge=0.01, a=0.54, fz=3.0, z2=1.8, tilt=tilt, pitch=0.6e-3 if tilt<20 else 0.45e-3, carry=fn)
    print(tilt, name, r, "psfL1", psf_l1(*d, crop_px=64), flush=True)
