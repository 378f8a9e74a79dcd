"""Analyse every bundled lens: paraxial table, real-ray EFL, RMS spots, layout and spot-diagram PNGs.

    python examples/lens_analysis.py [-o examples_out/lens_analysis]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tqdm import tqdm

from raywave.cli.lens_commands import format_info, lens_info, spot_table
from raywave.lens.build import bundled_lens_path, load_lens
from raywave.lens.analysis import distortion
from raywave.plotting import plot_layout, plot_spots

LENSES = ["singlet", "cooke_triplet", "double_gauss", "asphere_hk51"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", default="examples_out/lens_analysis")
    out = Path(ap.parse_args().output)
    out.mkdir(parents=True, exist_ok=True)
    for name in tqdm(LENSES, desc="lenses"):
        lens = load_lens(bundled_lens_path(name))
        text = format_info(lens_info(lens))
        spots = spot_table(lens)
        dist = distortion(lens).detach().tolist()
        lines = [text, "RMS spot radius (µm) per field (rows) and wavelength (columns):"]
        lines += [f"  {f:>6g}: " + "  ".join(f"{r:8.3f}" for r in row) for f, row in zip(spots["fields"], spots["rms_radius"])]
        lines.append("Distortion per field (%): " + ", ".join(f"{d:.3f}" for d in dist))
        (out / f"{name}.txt").write_text("\n".join(lines) + "\n")
        plot_layout(lens, out / f"{name}_layout.png")
        plot_spots(lens, out / f"{name}_spot.png")
    print(f"wrote tables and figures to {out}/")


if __name__ == "__main__":
    main()
