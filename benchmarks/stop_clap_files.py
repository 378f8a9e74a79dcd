"""Issue 44 / class E (h44e): the lens files whose stop carries its own clear aperture (a .zmx CLAP) beside a system
aperture, and what the loader makes of them: the stop's radius (the beam's hard edge), the paraxial EPD and F/#, and
the CLAP radius. Prints JSON; run it with two trees (PYTHONPATH) to see which files' reading changed.

    PYTHONPATH=. python benchmarks/stop_clap_files.py /tmp/optics/Optics [-o OUT.json]
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import emit_json  # noqa: E402

import raywave  # noqa: E402
from raywave.io import read_lens_spec  # noqa: E402
from raywave.lens.build import lens_from_spec  # noqa: E402


def one(path: Path) -> dict | None:
    """The stop of ``path`` when it has a circular aperture and the file a system aperture, else None."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            spec = read_lens_spec(path)
        except Exception:  # noqa: BLE001 - refusals are counted by benchmarks/lens_files.py
            return None
        stops = [i for i, s in enumerate(spec["surfaces"]) if s.get("stop")]
        i = stops[0] if stops else 0
        ap = spec["surfaces"][i].get("aperture")
        if not spec.get("system_aperture") or not ap or ap.get("shape") != "circle":
            return None
        try:
            lens = lens_from_spec(spec)
            p = lens.paraxial()
        except Exception as err:  # noqa: BLE001
            return {"error": str(err)[:200]}
        return {"stop": i, "clap": ap["radius"], "system_aperture": spec["system_aperture"],
                "stop_radius": lens.stop_radius(), "epd": p.epd, "fnum": p.fnum, "efl": p.efl}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("root")
    ap.add_argument("-o", "--output")
    a = ap.parse_args()
    root = Path(a.root)
    out = {}
    for f in sorted(p for p in root.rglob("*") if p.suffix.lower() == ".zmx"):
        r = one(f)
        if r is not None:
            out[str(f.relative_to(root))] = r
    emit_json({"root": str(root), "raywave": raywave.__file__, "files": out}, a.output)


if __name__ == "__main__":
    main()
