from disc import *
import time
for tilt in (0, 10.6, 30):
  for chart in (False, True):
    ep.SCALED_CARRY_CHART = chart
    r, d = case(edge=0.01, a=0.54, fz=3.0, z2=1.8, tilt=tilt, pitch=0.6e-3 if tilt<20 else 0.45e-3)
    print(tilt, chart, r, "psfL1", psf_l1(*d, crop_px=64), flush=True)
