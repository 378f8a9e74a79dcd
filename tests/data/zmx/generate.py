"""Writes the .zmx test corpus of tests/test_zmx_corpus.py (run once; the files are committed).

Each lens is a plausible design (patent-style doublet, microscope objective, Cooke triplets, relay, double Gauss,
molded odd-asphere singlet, cylinder and toric lenses, a CaF2 apochromat) written the way OpticStudio writes a
file: bookkeeping keys on every surface (HIDE, MIRR, SLAB, POPS), DIAM with its solve flags, GLAS with the
catalog nd / vd, CRLF line ends, and one file in UTF-16 LE with a BOM. The last thickness of each lens is its
paraxial image distance (found with raywave, rounded), so the image plane is near focus.

    PYTHONPATH=. python tests/data/zmx/generate.py
"""

from __future__ import annotations

import math
from pathlib import Path

HERE = Path(__file__).resolve().parent

HEADER = ["VERS 190513 80 123457 L123457", "MODE SEQ", "NAME {name}", "NOTE 0 {note}", "PFIL 0 0 0", "LANG 0",
          "UNIT MM X W X CM MR CPMM", "{aperture}", "ENVD 2.0E+1 1 0", "GFAC 0 0", "GCAT {gcat}",
          "RAIM 0 0 1 1 0 0 0 0 0", "PUSH 0 0 0 0 0 0", "SDMA 0 1 0", "FTYP {ftyp} 0 {nf} {nw} 0 0 0", "ROPD 2",
          "PICB 1", "XFLN {xfln}", "YFLN {yfln}", "FWGN {fwgn}", "VDXN {zeros}", "VDYN {zeros}", "VCXN {zeros}",
          "VCYN {zeros}", "VANN {zeros}"]
WAVES = [(0.4861327, 1), (0.5875618, 1), (0.6562725, 1)]


def _pad(values, n=12):
    return " ".join(repr(float(v)) if v else "0" for v in list(values) + [0.0] * (n - len(values)))


def zmx_text(name, note, aperture, gcat, surfaces, fields=(0.0,), ftyp=0, object_distance=None, xfields=None):
    """surfaces: dicts with type, curv, disz, glas (name, nd, vd) or None, diam, stop, coni, parm {i: v}."""
    fields = list(fields)
    xf = list(xfields) if xfields else [0.0] * len(fields)
    lines = [h.format(name=name, note=note, aperture=aperture, gcat=gcat, ftyp=ftyp, nf=len(fields),
                      nw=len(WAVES), xfln=_pad(xf), yfln=_pad(fields), fwgn=" ".join(["1"] * 12),
                      zeros=_pad([])) for h in HEADER]
    for i, (w, wt) in enumerate(WAVES, start=1):
        lines.append(f"WAVM {i} {w!r} {wt}")
    lines += ["PWAV 2", "POLS 1 0 1 0 0 1 0", "GLRS 1 0", "GSTD 0 100.000 100.000 100.000 100.000 100.000 100.000 0 1 "
              "1 0 0 1 1 1 1 1 1", "NSCD 100 500 0 1.0E-3 5 1.0E-6 0 0 0 0 0 0 1000000 0 2", "COFN QF \"COATING.DAT\" "
              "\"SCATTER_PROFILE.DAT\" \"ABG_DATA.DAT\" \"PROFILE.GRD\"", "SURF 0", "  TYPE STANDARD",
              '  CURV 0.0 0 0 0 0 ""', "  HIDE 0 0 0 0 0 0 0 0 0 0", "  MIRR 2 0", "  SLAB 1",
              "  DISZ " + ("INFINITY" if object_distance is None else repr(float(object_distance))),
              '  DIAM 0 0 0 0 1 ""', "  POPS 0 0 0 0 0 0 0 0 1 1 1 1 0 0 0 0"]
    for k, s in enumerate(surfaces, start=1):
        lines.append(f"SURF {k}")
        if s.get("stop"):
            lines.append("  STOP")
        if s.get("comm"):
            lines.append(f"  COMM {s['comm']}")
        lines += [f"  TYPE {s.get('type', 'STANDARD')}", f"  CURV {s.get('curv', 0.0)!r} 0 0 0 0 \"\"",
                  "  HIDE 0 0 0 0 0 0 0 0 0 0", "  MIRR 2 0", f"  SLAB {k + 1}"]
        for i, v in sorted(s.get("parm", {}).items()):
            lines.append(f"  PARM {i} {v!r}")
        lines.append(f"  DISZ {s['disz']!r}")
        if s.get("glas"):
            g, nd, vd = s["glas"]
            lines.append(f"  GLAS {g} 0 0 {nd} {vd} 0 0 0 0 0 0")
        if s.get("coni"):
            lines.append(f"  CONI {s['coni']!r}")
        lines.append(f"  DIAM {s.get('diam', 10.0)!r} {1 if s.get('stop') else 0} 0 0 1 \"\"")
        lines.append("  POPS 0 0 0 0 0 0 0 0 1 1 1 1 0 0 0 0")
    n = len(surfaces) + 1
    lines += [f"SURF {n}", "  TYPE STANDARD", '  CURV 0.0 0 0 0 0 ""', "  HIDE 0 0 0 0 0 0 0 0 0 0", "  MIRR 2 0",
              f"  SLAB {n + 1}", "  DISZ 0", '  DIAM 10 0 0 0 1 ""', "  POPS 0 0 0 0 0 0 0 0 1 1 1 1 0 0 0 0",
              "TOL TOFF 0 0 0 0 0 0 0", "MNUM 1 1", "MOFF 0 1 \"\" 0 0 0 1 1 \"\" 0 \"\""]
    return "\r\n".join(lines) + "\r\n"


def S(r=math.inf, t=0.0, glas=None, **kw):
    return dict(curv=0.0 if math.isinf(r) else 1.0 / r, disz=t, glas=glas, **kw)


NBAF10, NSF10, NSK16, F2 = ("N-BAF10", 1.67003, 47.11), ("N-SF10", 1.72828, 28.53), ("N-SK16", 1.62041, 60.32), \
    ("F2", 1.62004, 36.37)
NBK7, SF5, CAF2 = ("N-BK7", 1.5168, 64.17), ("SF5", 1.67270, 32.21), ("CAF2", 1.43385, 94.99)


def achromat(scale=1.0, reverse=False, last=0.0):
    """Thorlabs AC254-100-A style cemented achromat (N-BAF10 / N-SF10), f ~ 100·scale mm."""
    r = [62.75 * scale, -45.71 * scale, -128.23 * scale]
    t = [4.0 * scale, 2.5 * scale]
    g = [NBAF10, NSF10]
    if reverse:
        r = [-x for x in r[::-1]]
        t, g = t[::-1], g[::-1]
    d = 12.7 * scale
    return [S(r[0], t[0], g[0], diam=d), S(r[1], t[1], g[1], diam=d), S(r[2], last, None, diam=d)]


COOKE = lambda last: [S(22.01359, 3.25896, NSK16, diam=6.0), S(-435.7604, 6.007551, None, diam=6.0),  # noqa: E731
                      S(-22.21328, 0.9994, F2, diam=4.8), S(20.29192, 4.750409, None, diam=4.2, stop=True),
                      S(79.68364, 2.952076, NSK16, diam=6.0), S(-18.3783, last, None, diam=6.0)]


def lenses():
    """name -> (zmx kwargs, encoding)."""
    out = {}
    out["doublet_fnum"] = (dict(
        name="US 4,123,456 Example 1 (cemented achromat f=100)", note="patent-style doublet, image-space F/4",
        aperture="FNUM 4 0", gcat="SCHOTT", surfaces=[dict(s, stop=(i == 0)) for i, s in enumerate(achromat())],
        fields=(0.0, 1.0, 2.0)), "utf-16")
    mic = achromat(0.2, reverse=True, last=1.0) + [S(math.inf, 1.0, None, diam=3.0, stop=True, comm="STOP")] + \
        achromat(0.4, reverse=True)
    out["microscope_obna"] = (dict(
        name="10x finite objective (Lister type)", note="object-space NA 0.1, object 16 mm", aperture="OBNA 0.1 0",
        gcat="SCHOTT", surfaces=mic, fields=(0.0, 0.3, 0.5), ftyp=1, object_distance=16.0), "utf-8")
    out["cooke_floa"] = (dict(
        name="Cooke triplet, float by stop size", note="stop semi-diameter 4.2 mm", aperture="FLOA",
        gcat="SCHOTT", surfaces=COOKE(0.0), fields=(0.0, 14.0, 20.0)), "utf-8")
    out["cooke_pwfn"] = (dict(
        name="Cooke triplet at 400 mm, paraxial working F/6", note="finite conjugate", aperture="FNUM 6 1",
        gcat="SCHOTT", surfaces=COOKE(0.0), fields=(0.0, 20.0, 40.0), ftyp=1, object_distance=400.0), "utf-8")
    relay = achromat(reverse=True, last=20.0) + [S(math.inf, 20.0, None, diam=8.0, stop=True)] + achromat()
    out["relay_ocan"] = (dict(
        name="1:1 relay, two AC254-100", note="object cone angle 3 degrees", aperture="OBNA 3 1", gcat="SCHOTT",
        surfaces=relay, fields=(0.0, 2.0, 4.0), ftyp=1, object_distance=91.0), "utf-8")
    dg = [S(54.153246, 8.746658, ("S-BAH11", 1.66672, 48.32), diam=29.0), S(152.52192, 0.5, None, diam=27.0),
          S(35.950624, 14.0, ("S-LAH66", 1.77250, 49.60), diam=24.0), S(math.inf, 3.776966, ("H-ZF52", 1.84666, 23.78),
                                                                        diam=21.0),
          S(22.269925, 14.253059, None, diam=15.0), S(math.inf, 12.428, None, diam=13.0, stop=True),
          S(-25.685033, 3.776966, ("H-ZF52", 1.84666, 23.78), diam=14.0),
          S(math.inf, 10.833929, ("TAFD5F", 1.83481, 42.72), diam=18.0), S(-36.980221, 0.5, None, diam=19.0),
          S(196.41751, 6.858175, ("S-LAH66", 1.77250, 49.60), diam=21.0), S(-67.14755, 0.0, None, diam=21.0)]
    out["double_gauss_ohara_cdgm_hoya"] = (dict(
        name="Double Gauss f/3 (OHARA, CDGM, HOYA glasses)", note="glasses from three catalogs", aperture="ENPD 33.3333",
        gcat="OHARA CDGM HOYA", surfaces=dg, fields=(0.0, 10.0, 14.0)), "utf-8")
    odd = [dict(S(4.2, 2.6, ("E48R", 1.5310, 56.04), diam=2.4, stop=True), type="ODDASPHE", coni=-0.8,
                parm={1: 0.0, 2: 0.0, 3: 2.1e-3, 4: -1.4e-3, 5: 3.0e-4, 6: -2.2e-5, 7: 0.0, 8: 0.0}),
           dict(S(-11.0, 0.0, None, diam=2.4), type="ODDASPHE",
                parm={1: 0.0, 2: 0.0, 3: 4.0e-3, 4: -6.0e-4, 5: 0.0, 6: 0.0, 7: 0.0, 8: 0.0})]
    out["singlet_oddasphe"] = (dict(
        name="Molded ZEONEX singlet, odd aspheres", note="f ~ 6 mm, odd terms r^3..r^6", aperture="ENPD 3.0",
        gcat="MISC SCHOTT", surfaces=odd, fields=(0.0, 5.0, 10.0)), "utf-8")
    cyl = [dict(S(51.68, 5.0, NBK7, diam=12.7, stop=True), type="TOROIDAL", parm={0: 0.0, 1: 0.0}),
           S(math.inf, 0.0, None, diam=12.7)]
    out["cylinder_toroidal"] = (dict(
        name="Plano-convex cylinder lens f=100 (LJ1567 style)", note="TOROIDAL, radius of rotation 0 = infinite",
        aperture="ENPD 10", gcat="SCHOTT", surfaces=cyl, fields=(0.0, 1.0, 2.0)), "utf-8")
    toric = [dict(S(40.0, 4.0, NBK7, diam=10.0, stop=True), type="TOROIDAL",
                  parm={0: 0.0, 1: 60.0, 2: 0.0, 3: -2.0e-6, 4: 1.0e-9}),
             dict(S(-120.0, 0.0, None, diam=10.0), type="TOROIDAL", parm={1: -200.0})]
    out["toric_singlet"] = (dict(
        name="Toric singlet (y asphere)", note="TOROIDAL with finite radii of rotation", aperture="FNUM 8 0",
        gcat="SCHOTT", surfaces=toric, fields=(0.0, 3.0)), "utf-8")
    apo = [S(60.0, 6.0, CAF2, diam=8.0, stop=True), S(-42.0, 0.2, None, diam=8.0),
           S(-41.0, 2.5, SF5, diam=8.0), S(-120.0, 0.0, None, diam=8.0)]
    out["caf2_doublet_infrared_gcat"] = (dict(
        name="CaF2 / SF5 air-spaced doublet", note="GCAT names INFRARED, which raywave does not bundle",
        aperture="ENPD 12", gcat="INFRARED SCHOTT", surfaces=apo, fields=(0.0, 1.0)), "utf-8")
    # ---- mirrors and coordinate breaks (issue 18): OpticStudio's conventions, thicknesses negative after a mirror
    fold = achromat(last=40.0)
    fold[0]["stop"] = True
    fold += [CB(tilt_x=45.0, comm="fold in"), S(math.inf, 0.0, MIRROR, diam=12.0, comm="fold mirror"),
             CB(tilt_x=45.0, t=-60.0, comm="fold out")]
    out["fold_mirror_doublet"] = (dict(
        name="AC254-100 with a 45 degree fold mirror", note="COORDBRK pair around a flat mirror", aperture="ENPD 10",
        gcat="SCHOTT", surfaces=fold, fields=(0.0, 1.0, 2.0)), "utf-8")
    newt = [S(-1200.0, -500.0, MIRROR, diam=80.0, stop=True, coni=-1.0, comm="parabolic primary"),
            CB(tilt_x=45.0, comm="diagonal in"), S(math.inf, 0.0, MIRROR, diam=30.0, comm="diagonal"),
            CB(tilt_x=45.0, t=100.0, comm="diagonal out")]
    out["newtonian_telescope"] = (dict(
        name="Newtonian telescope 150 mm F/4", note="parabola + flat diagonal, COORDBRK fold", aperture="ENPD 150",
        gcat="SCHOTT", surfaces=newt, fields=(0.0, 0.2, 0.4)), "utf-8")
    cass = [S(-800.0, -300.0, MIRROR, diam=100.0, stop=True, coni=-1.0, comm="primary (paraboloid)"),
            S(-266.6666666666667, 400.0, MIRROR, diam=30.0, coni=-2.7777777777777777, comm="secondary (hyperboloid)")]
    out["cassegrain"] = (dict(
        name="Classical Cassegrain 200 mm F/8", note="two mirrors on axis, thickness negative after the primary",
        aperture="ENPD 200", gcat="SCHOTT", surfaces=cass, fields=(0.0, 0.1, 0.2)), "utf-8")
    dec = [S(math.inf, 5.0, None, diam=6.0, stop=True, comm="stop"),
           CB(dy=0.5, tilt_x=2.0, comm="element decentre and tilt")] + achromat(0.5, last=3.0) + \
        [CB(tilt_x=-2.0, comm="undo tilt"), CB(dy=-0.5, t=45.0, comm="undo decentre")]
    out["decentered_tilted_doublet"] = (dict(
        name="Achromat f=50 decentred 0.5 mm and tilted 2 degrees", note="tolerancing case: COORDBRK before and after",
        aperture="ENPD 6", gcat="SCHOTT", surfaces=dec, fields=(0.0, 1.0, 2.0)), "utf-8")
    return out


MIRROR = ("MIRROR", 1.5, 40.0)


def CB(dx=0.0, dy=0.0, tilt_x=0.0, tilt_y=0.0, tilt_z=0.0, order=0, t=0.0, comm=""):
    """An OpticStudio coordinate break: PARM 1..6 = decentre x, y, tilt x, y, z (degrees), order flag."""
    return dict(type="COORDBRK", curv=0.0, disz=t, glas=None, diam=0.0, comm=comm,
                parm={1: dx, 2: dy, 3: tilt_x, 4: tilt_y, 5: tilt_z, 6: order})


def finish(kw):
    """Set the last thickness to the paraxial image distance (rounded to 1 µm), found with raywave."""
    import warnings

    from raywave.io.zmx import read_zmx
    from raywave.lens import paraxial
    from raywave.lens.build import lens_from_spec

    if kw["name"].startswith("Achromat f=50 decentred"):
        # no paraxial image for a decentred element: the image distance of the same doublet centred
        centred = [dict(s) for s in kw["surfaces"] if s.get("type") != "COORDBRK"]
        bfl = finish(dict(kw, name="centred", surfaces=centred))["surfaces"][-1]["disz"]
        kw["surfaces"][-1]["disz"] = round(bfl - kw["surfaces"][-3]["disz"], 3)
        return kw
    tmp = HERE / "_tmp.zmx"
    tmp.write_text(zmx_text(**kw), encoding="utf-8")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            lens = lens_from_spec(read_zmx(tmp))
        if kw["name"].startswith("Classical Cassegrain"):
            return kw  # the image distance is the design's (400 mm after the secondary)
        p = lens.paraxial()
        if lens.is_folded or lens.has_mirrors:  # along the unfolded axis; thickness and gap change alike
            pos = float(paraxial.axial_vertex_positions(lens)[-1].detach())
            gap = float(paraxial.axial_gaps(lens)[-1].detach())
            kw["surfaces"][-1]["disz"] = round(kw["surfaces"][-1]["disz"] + p.image_z_paraxial - pos - gap, 3)
        else:
            kw["surfaces"][-1]["disz"] = round(p.image_z_paraxial - float(lens.vertex_z()[-1].detach()), 3)
    finally:
        tmp.unlink()
    return kw


def main():
    for name, (kw, enc) in lenses().items():
        text = zmx_text(**finish(kw))
        data = b"\xff\xfe" + text.encode("utf-16-le") if enc == "utf-16" else text.encode("utf-8")
        (HERE / f"{name}.zmx").write_bytes(data)
        print(name, enc, len(data), "bytes")


if __name__ == "__main__":
    main()
