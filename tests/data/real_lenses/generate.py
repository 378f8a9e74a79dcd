"""Writes the real-lens .zmx files of tests/test_stop_edge_real_lenses.py (issue 19: the exit-pupil stop edge on
lenses a user loads; run once, the files are committed). Kept out of tests/data/zmx so the .zmx reader corpus
(tests/test_zmx_corpus.py) stays as it is. Same writer as that corpus (OpticStudio style).

* ``singlet_nbk7_50.zmx``: a 50 mm N-BK7 plano-convex singlet (Thorlabs LA1131 style: R 25.75 mm, 5.3 mm thick,
  curved side to the object), 12.5 mm entrance pupil (F/4), fields 0 / 3.5 / 5 degrees; image at the paraxial
  focus.
* ``asphere_f13_nsf11.zmx``: an F/1.3 N-SF11 plano-convex asphere, f = 27.3 mm, 21 mm entrance pupil, flat side
  to the object and a hyperboloid (conic −n²) behind it: free of spherical aberration on axis; fields 0 / 0.7 /
  1 degree (coma grows fast off axis).

    PYTHONPATH=. python tests/data/real_lenses/generate.py
"""

import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "zmx"))

from generate import NBK7, S, finish, zmx_text  # noqa: E402

NSF11 = ("N-SF11", 1.78472, 25.68)


def lenses():
    out = {}
    out["singlet_nbk7_50"] = dict(
        name="Plano-convex N-BK7 f=50 (LA1131 style)", note="12.5 mm entrance pupil, F/4", aperture="ENPD 12.5",
        gcat="SCHOTT", surfaces=[S(25.75, 5.3, NBK7, diam=12.7, stop=True), S(math.inf, 0.0, None, diam=12.7)],
        fields=(0.0, 3.5, 5.0))
    n = NSF11[1]
    f = 27.3
    out["asphere_f13_nsf11"] = dict(
        name="F/1.3 plano-convex asphere N-SF11 f=27.3", note="hyperboloid, conic -n^2: no spherical aberration",
        aperture="ENPD 21", gcat="SCHOTT",
        surfaces=[S(math.inf, 8.0, NSF11, diam=11.0, stop=True), S(-f * (n - 1), 0.0, None, diam=11.0, coni=-n * n)],
        fields=(0.0, 0.7, 1.0))
    return out


def main():
    for name, kw in lenses().items():
        (HERE / f"{name}.zmx").write_bytes(zmx_text(**finish(kw)).encode("utf-8"))
        print(name)


if __name__ == "__main__":
    main()
