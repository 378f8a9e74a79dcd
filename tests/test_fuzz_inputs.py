"""Seeded fuzzing of everything a user hands raywave (issue 16): lens files (.json, .zmx), DOE sections and
phase maps, training configs, and the CLI's arguments.

Every mutated input must either load and trace to finite numbers, or be refused with one of raywave's errors
(all ``ValueError`` subclasses: docs/conventions.md, "Errors") whose message names the file; never another
exception type, never a traceback from the CLI (exit status 2, one ``raywave: error:`` line).

Default suite: a fixed sample of cases per family (fast); ``slow``: more seeds."""

from __future__ import annotations

import contextlib
import io
import json
import math
import random
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from raywave.cli.main import main
from raywave.io import write_lens_spec
from raywave.lens.build import BUNDLED

LENS_NAMES = sorted(p.stem for p in BUNDLED.glob("*.json"))
NASTY_NUMBERS = [float("nan"), math.inf, -math.inf, 0.0, -1.0, -1e-300, 1e-300, 1e308, -1e308, 1e12, 3, -5, 0.5]
NASTY_VALUES = NASTY_NUMBERS + ["abc", "", "inf", None, True, [], {}, [1.0, 2.0], {"a": 1}]
NASTY_TOKENS = ["nan", "NaN", "INF", "-INF", "inf", "1e400", "-1e400", "0", "-5", "1e308", "1e-300", "abc", "",
                "0.5", "3", "1e12", "-0"]


# ------------------------------------------------------------------ outcome of one file
def _accepted_error(err: BaseException, path: Path) -> bool:
    """A raywave refusal: a ValueError subclass (every raywave error type is one) naming the file."""
    return isinstance(err, ValueError) and (path.name in str(err) or str(path) in str(err))


def _try_file(path: Path, psf: bool = False, lens_only: bool = False) -> str:
    """'loaded' (and traced to finite numbers) or 'refused' (a clean raywave error); anything else fails.
    ``lens_only``: the refractive lens alone (``load_lens``; a blank DOE's sizing costs seconds per file)."""
    from raywave import load_lens
    from raywave.hybrid.build import load_hybrid
    from raywave.lens.sources import point_source_rays

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            hl = None if lens_only else load_hybrid(path)
            lens = load_lens(path) if lens_only else hl.lens
        except Exception as err:  # noqa: BLE001 - the point of the test
            assert _accepted_error(err, path), f"{path.name}: {type(err).__name__}: {err}"
            return "refused"
        try:
            field = max(lens.fields, key=abs) if lens.field_type == "angle" else 0.0
            rays = point_source_rays(lens, (0.0, field), pupil=("grid", 5))
            out = lens.trace_to_image(rays)
            if psf:
                res = hl.psf((0.0, 0.0), ks=8, rays=8)
        except ValueError:  # a raywave error at trace time (e.g. a stop without aperture)
            return "refused"
        except Exception as err:  # noqa: BLE001
            raise AssertionError(f"{path.name}: loaded, then {type(err).__name__}: {err}") from err
    v = out.valid
    assert bool(torch.isfinite(out.o[v]).all()) and bool(torch.isfinite(out.opl[v]).all()), path.name
    if psf:
        assert bool(torch.isfinite(res).all()), path.name
    return "loaded"


# ------------------------------------------------------------------ mutations
def _paths(obj, prefix=()):
    """Every key path (tuple) in a JSON-like object."""
    out = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.append(prefix + (k,))
            out += _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out.append(prefix + (i,))
            out += _paths(v, prefix + (i,))
    return out


def _mutate_json(spec: dict, rng: random.Random) -> dict:
    spec = json.loads(json.dumps(spec))
    for _ in range(rng.choice([1, 1, 2])):
        paths = _paths(spec)
        if not paths:
            break
        path = rng.choice(paths)
        parent = spec
        for k in path[:-1]:
            parent = parent[k]
        key = path[-1]
        if rng.random() < 0.2:
            if isinstance(parent, dict):
                del parent[key]
            else:
                parent.pop(key)
        else:
            parent[key] = rng.choice(NASTY_VALUES)
    return spec


def _mutate_bytes(raw: bytes, rng: random.Random) -> bytes:
    kind = rng.choice(["truncate", "flip", "insert", "utf16", "latin1", "bom"])
    if kind == "truncate":
        return raw[: rng.randrange(len(raw))]
    if kind == "flip":
        b = bytearray(raw)
        for _ in range(rng.randint(1, 4)):
            b[rng.randrange(len(b))] = rng.randrange(256)
        return bytes(b)
    if kind == "insert":
        i = rng.randrange(len(raw))
        return raw[:i] + bytes(rng.choice([b"\xff\xfe", b"\x00", b"\xc3\x28", b"\x80"])) + raw[i:]
    if kind == "utf16":
        return raw.decode("utf-8", "replace").encode(rng.choice(["utf-16", "utf-16-le", "utf-16-be"]))
    if kind == "latin1":
        return raw.decode("utf-8", "replace").replace("a", "ä").encode("latin-1", "replace")
    return b"\xef\xbb\xbf" + raw


def _mutate_zmx(text: str, rng: random.Random) -> str:
    lines = text.splitlines()
    for _ in range(rng.choice([1, 1, 2])):
        i = rng.randrange(len(lines))
        toks = lines[i].split(" ")
        op = rng.random()
        if op < 0.15:
            del lines[i]
        elif op < 0.25:
            lines.insert(i, lines[i])
        else:
            num = [j for j, t in enumerate(toks) if t and (t[0].isdigit() or t[0] in "-.") or t.upper() == "INFINITY"]
            if num:
                toks[rng.choice(num)] = rng.choice(NASTY_TOKENS)
            else:
                toks.append(rng.choice(NASTY_TOKENS))
            lines[i] = " ".join(toks)
    return "\n".join(lines) + "\n"


def _hybrid_spec(tmp: Path, kind: str) -> dict:
    """A small hybrid lens file (asphere + 64² DOE): a phase map, or a BINARY_2 model."""
    spec = json.loads((BUNDLED / "asphere_hk51.json").read_text())
    doe = {"distance": 0.7, "pitch": 0.04, "shape": [64, 64], "aperture": "square"}
    if kind == "map":
        np.save(tmp / "phase.npy", np.random.default_rng(0).normal(size=(64, 64)))
        doe["phase"] = "phase.npy"
    else:
        doe["phase_model"] = {"type": "binary_2", "order": 1.0, "norm_radius": 1.0,
                              "coefficients": [-30.0, 2.0]}
    spec["doe"] = doe
    return spec


def _file_cases(tmp: Path, seed: int, n: int):
    """``n`` mutated files from seed: (path, whether to compute a PSF)."""
    rng = random.Random(seed)
    bases = {name: json.loads((BUNDLED / f"{name}.json").read_text()) for name in LENS_NAMES}
    bases["hybrid_map"] = _hybrid_spec(tmp, "map")
    bases["hybrid_b2"] = _hybrid_spec(tmp, "b2")
    zmx = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name in LENS_NAMES + ["hybrid_b2"]:
            p = tmp / f"base_{name}.zmx"
            write_lens_spec(bases[name], p, encoding="utf-8")
            zmx[name] = p.read_text(encoding="utf-8")
    out = []
    for i in range(n):
        kind = rng.choice(["json", "json", "json", "zmx", "zmx", "bytes", "npy"])
        name = rng.choice(sorted(bases))
        if kind == "npy":  # the DOE's phase map file itself
            name = "hybrid_map"
            spec = json.loads(json.dumps(bases[name]))
            spec["doe"]["phase"] = f"phase{seed}_{i}.npy"
            q = tmp / spec["doe"]["phase"]
            bad = rng.choice(["nan", "inf", "huge", "3d", "1d", "empty", "shape", "truncated", "text"])
            arr = {"nan": np.full((64, 64), np.nan), "inf": np.full((64, 64), np.inf), "huge": np.full((64, 64), 1e300),
                   "3d": np.zeros((2, 64, 64)), "1d": np.zeros(64), "empty": np.zeros((0, 0)),
                   "shape": np.zeros((63, 65))}.get(bad)
            if arr is not None:
                np.save(q, arr)
            elif bad == "truncated":
                np.save(q, np.zeros((64, 64)))
                q.write_bytes(q.read_bytes()[:100])
            else:
                q.write_text("not a numpy file")
            p = tmp / f"case{seed}_{i}.json"
            p.write_text(json.dumps(spec), encoding="utf-8")
        elif kind == "json":
            p = tmp / f"case{seed}_{i}.json"
            text = json.dumps(_mutate_json(bases[name], rng), indent=1)  # NaN / Infinity tokens included
            p.write_text(text, encoding="utf-8")
        elif kind == "zmx":
            name = rng.choice(sorted(zmx))
            p = tmp / f"case{seed}_{i}.zmx"
            enc = rng.choice(["utf-8", "utf-16"])
            p.write_bytes(_mutate_zmx(zmx[name], rng).encode(enc))
        else:
            ext = rng.choice(["json", "zmx"])
            src = json.dumps(bases[name], indent=1) if ext == "json" else zmx.get(name, zmx["singlet"])
            p = tmp / f"case{seed}_{i}.{ext}"
            p.write_bytes(_mutate_bytes(src.encode("utf-8"), rng))
        out.append((p, name.startswith("hybrid")))
    return out


#: hybrid files traced to a PSF in the quick (default-suite) run: each costs the DOE's sizing and a PSF (~5 s)
QUICK_PSFS = 2


def _run_files(tmp: Path, seeds, n: int, quick: bool = False) -> dict:
    """Counts of loaded / refused fuzzed files. ``quick``: files that are not traced to a PSF are read as lenses
    only, and at most :data:`QUICK_PSFS` hybrids are traced to a PSF (a blank DOE's sizing costs seconds per file;
    the slow test sizes and traces them all)."""
    counts = {"loaded": 0, "refused": 0}
    psfs = 0
    for seed in seeds:
        for path, psf in _file_cases(tmp, seed, n):
            psf = psf and not (quick and psfs >= QUICK_PSFS)
            psfs += psf
            counts[_try_file(path, psf=psf, lens_only=quick and not psf)] += 1
    return counts


def test_fuzzed_lens_and_doe_files_load_or_are_refused_cleanly(tmp_path):
    counts = _run_files(tmp_path, range(2), 60, quick=True)  # every file sized as a hybrid: the slow test below
    print(f"\nfuzzed files: {counts}")
    assert counts["loaded"] > 5 and counts["refused"] > 60, counts


@pytest.mark.slow
def test_many_fuzzed_lens_and_doe_files(tmp_path):
    counts = _run_files(tmp_path, range(100, 120), 80)
    print(f"\nfuzzed files (slow): {counts}")


# ------------------------------------------------------------------ CODE V .seq files
SEQ_DIR = Path(__file__).parent / "data" / "codev"


def _mutate_seq(text: str, rng: random.Random) -> str:
    """One or two line edits of a .seq file: drop, repeat, cut a command's arguments short, or put a nasty token
    in place of one of them."""
    lines = text.splitlines()
    for _ in range(rng.choice([1, 1, 2])):
        i = rng.randrange(len(lines))
        toks = lines[i].split()
        op = rng.random()
        if op < 0.1:
            del lines[i]
        elif op < 0.2:
            lines.insert(i, lines[i])
        elif op < 0.45 and toks:
            lines[i] = " ".join(toks[:rng.randrange(1, len(toks) + 1)])
        elif toks:
            toks[rng.randrange(len(toks))] = rng.choice(NASTY_TOKENS + ["'x'", ";"])
            lines[i] = " ".join(toks)
    return "\n".join(lines) + "\n"


def _run_seq(tmp: Path, seeds, n: int) -> dict:
    bases = sorted(SEQ_DIR.glob("*.seq"))
    counts = {"loaded": 0, "refused": 0}
    for seed in seeds:
        rng = random.Random(seed)
        for i in range(n):
            p = tmp / f"seq{seed}_{i}.seq"
            p.write_text(_mutate_seq(rng.choice(bases).read_text(), rng), encoding="utf-8")
            counts[_try_file(p, lens_only=True)] += 1
    return counts


def test_fuzzed_codev_files_load_or_are_refused_cleanly(tmp_path):
    """A command cut short (``K`` or ``REF`` without its value) or given a nasty number is a one-line error naming
    the file and line, never an IndexError / OverflowError."""
    counts = _run_seq(tmp_path, range(3), 40)
    print(f"\nfuzzed .seq files: {counts}")
    assert counts["loaded"] > 5 and counts["refused"] > 5, counts


@pytest.mark.slow
def test_many_fuzzed_codev_files(tmp_path):
    print(f"\nfuzzed .seq files (slow): {_run_seq(tmp_path, range(100, 140), 80)}")


@pytest.mark.parametrize("line,match", [("K", r"K: a value is missing"), ("REF", r"REF: a value is missing"),
                                        ("REF nan", r"REF: 'nan' is not a whole number"),
                                        ("REF 1e400", r"REF: '1e400' is not a whole number"),
                                        ("REF 1.5", r"REF: '1.5' is not a whole number")])
def test_codev_commands_without_their_value_are_named_errors(tmp_path, line, match):
    from raywave.io import read_lens_spec
    from raywave.io.errors import LensFileError

    text = (SEQ_DIR / "cooke_triplet.seq").read_text()
    if line.startswith("K"):  # a conic on the first surface
        text = text.replace("  CCY 0; THC 0\n", f"  {line}\n", 1)
    else:
        text = text.replace("REF   2", line, 1)
    p = tmp_path / "bad.seq"
    p.write_text(text, encoding="utf-8")
    with pytest.raises(LensFileError, match=r"bad\.seq:\d+: .*" + match):
        read_lens_spec(p)


# ------------------------------------------------------------------ the issue's file examples
def _zmx_of(tmp: Path, name: str = "singlet") -> str:
    p = tmp / f"{name}.zmx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_lens_spec(json.loads((BUNDLED / f"{name}.json").read_text()), p, encoding="utf-8")
    return p.read_text(encoding="utf-8")


@pytest.mark.parametrize("old,new,match", [
    ("CURV 0.009765625", "CURV INF", r"CURV INF is not a finite number"),
    ("FTYP 0 0 3 3", "FTYP 0 0 1e400 3", r"FTYP entry 3: '1e400' is not an integer"),
    ("CURV 0.009765625", "CURV nan", r"CURV nan is not a finite number"),
    ("PWAV 2", "PWAV 1e400", r"PWAV: '1e400' is not an integer"),
])
def test_zmx_crash_examples_are_one_line_errors(tmp_path, capsys, old, new, match):
    text = _zmx_of(tmp_path)
    assert old in text
    p = tmp_path / "bad.zmx"
    p.write_text(text.replace(old, new, 1), encoding="utf-8")
    from raywave.io import LensFileError, read_lens_spec

    with pytest.raises(LensFileError, match=r"bad\.zmx:\d+: .*" + match):
        read_lens_spec(p)
    assert main(["info", str(p)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 1 and err.startswith("raywave: error:")


def _binary2_zmx(tmp: Path, xdat=None, parm0="1", norm="1.0") -> Path:
    spec = _hybrid_spec(tmp, "b2")
    p = tmp / "b2.zmx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_lens_spec(spec, p, encoding="utf-8")
    text = p.read_text(encoding="utf-8")
    lines = []
    for ln in text.splitlines():
        s = ln.strip()
        if s.startswith("PARM 0 "):
            ln = f"  PARM 0 {parm0}"
        if s.startswith("XDAT 2 "):
            ln = f"  XDAT 2 {norm} 0 0 1 0 0 \"\""
        if xdat is not None and s.startswith("XDAT 3 "):
            ln = f"  XDAT {xdat} -30.0 0 0 1 0 0 \"\""
        lines.append(ln)
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return p


def test_binary2_with_an_invalid_xdat_index_is_refused(tmp_path):
    """XDAT −5 used to drop the coefficient silently (a blank DOE, exit 0)."""
    from raywave.io import LensFileError, read_lens_spec

    with pytest.raises(LensFileError, match=r"b2\.zmx:\d+: surface \d+: XDAT index: -5 is out of range"):
        read_lens_spec(_binary2_zmx(tmp_path, xdat=-5))
    with pytest.raises(LensFileError, match=r"XDAT 9 = -30.0 lies beyond the 2 terms"):
        read_lens_spec(_binary2_zmx(tmp_path, xdat=9))


@pytest.mark.parametrize("kw", [{"parm0": "1e308"}, {"norm": "1e-300"}])
def test_binary2_phase_overflow_is_refused_not_an_all_nan_psf(tmp_path, kw):
    """PARM 0 1e308 or a normalisation radius 1e-300 made an all-NaN PSF that the CLI blamed on vignetting."""
    from raywave.hybrid.build import load_hybrid
    from raywave.io import LensFileError

    p = _binary2_zmx(tmp_path, **kw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(LensFileError, match=r"b2\.zmx: doe\.phase_model: the binary_2 phase model's phase is"):
            load_hybrid(p, doe_pitch=0.04, doe_size=2.56)


def test_binary2_norm_radius_in_a_json_lens_file_is_refused(tmp_path):
    from raywave.hybrid.build import load_hybrid

    spec = _hybrid_spec(tmp_path, "b2")
    spec["doe"]["phase_model"]["norm_radius"] = 1e-300
    p = tmp_path / "b2.json"
    p.write_text(json.dumps(spec))
    with pytest.raises(ValueError, match=r"b2\.json: doe\.phase_model: .*not finite|b2\.json: doe\.phase_model: .*inf"):
        load_hybrid(p)


def test_a_non_finite_psf_raises_a_named_error():
    """Whatever slips past the load-time checks: a NaN PSF is a NonFiniteError, never returned."""
    from raywave.doe import PixelDOE
    from raywave.hybrid import HybridLens
    from raywave.lens.build import bundled_lens_path, load_lens
    from raywave.utils.errors import NonFiniteError

    doe = PixelDOE(torch.zeros(32, 32), 0.1)
    with torch.no_grad():
        doe.phase_map.fill_(1e300)
        doe.phase_scale = 1e300  # inf phase
    hl = HybridLens(load_lens(bundled_lens_path("asphere_hk51")), doe, 0.7)
    with warnings.catch_warnings(), pytest.raises(NonFiniteError, match=r"PSF of source 0 .* is not finite"):
        warnings.simplefilter("ignore")
        hl.psf((0.0, 0.0), ks=8, rays=8)


@pytest.mark.parametrize("value, distance", [(120.0, 1000.0), (90.0, 1000.0), (-90.0, 1000.0), (180.0, "inf"),
                                             (-180.0, "inf"), (1e12, "inf")])
def test_field_angles_out_of_range_are_refused(tmp_path, value, distance):
    """At or beyond 90° for a finite object; at or beyond 180° for an object at infinity (a fisheye's field between
    90° and 180° is read: tests/test_lens_files_fisheye.py)."""
    from raywave.io import LensFileError
    from raywave.lens.build import load_lens

    spec = json.loads((BUNDLED / "singlet.json").read_text())
    spec["fields"]["values"] = [0.0, value]
    spec["object"]["distance"] = distance
    p = tmp_path / "wide.json"
    p.write_text(json.dumps(spec))
    with pytest.raises(LensFileError, match=r"wide\.json:\d+: fields\.values\[1\]: field angle"):
        load_lens(p)
    if distance == "inf":
        assert main(["spot", "singlet", "--fields", f"0,{value}"]) == 2
    assert main(["info", str(p), "--json"]) == 2


@pytest.mark.parametrize("argv", [["--pitch", "1e6"], ["--pitch", "1e-12"]])
def test_doe_export_refuses_pitches_the_mask_file_cannot_hold(tmp_path, capsys, argv):
    np.save(tmp_path / "ph.npy", np.random.default_rng(0).uniform(0, 6.28, (16, 16)))
    out = tmp_path / "masks"
    assert main(["doe", "export", str(tmp_path / "ph.npy"), "-o", str(out), "--no-png"] + argv) == 2
    err = capsys.readouterr().err
    # (a pitch above 0.1 mm is refused by the one pitch check first, issue 45)
    assert ("32-bit" in err or "database unit" in err or "larger than any DOE" in err) and "Traceback" not in err
    assert not (out / "masks.gds").exists()


@pytest.mark.parametrize("extra", [["--doe-pitch", "1e-6"], ["--oversample", "1000000"]])
def test_a_doe_grid_too_large_for_memory_is_refused_before_allocating(capsys, extra):
    assert main(["psf", "singlet", "--ks", "8", "--rays", "8"] + extra) == 2
    err = capsys.readouterr().err
    assert "needs about" in err and "available" in err and ("--doe-pitch" in err or "--oversample" in err)


def test_oversample_in_a_lens_files_doe_is_checked_against_memory(tmp_path):
    from raywave.hybrid.build import load_hybrid
    from raywave.utils.errors import MemoryLimitError

    spec = _hybrid_spec(tmp_path, "b2")
    spec["doe"]["oversample"] = 1000000
    p = tmp_path / "big.json"
    p.write_text(json.dumps(spec))
    with warnings.catch_warnings(), pytest.raises(MemoryLimitError, match=r"needs about .* available"):
        warnings.simplefilter("ignore")
        load_hybrid(p).psf((0.0, 0.0), ks=8, rays=8)  # refused when the lens is built (issue 45), before the PSF


def test_json_output_never_holds_nan_or_infinity(capsys):
    assert main(["info", "singlet", "--wavelength", "0", "--json"]) == 2
    assert "--wavelength" in capsys.readouterr().err
    from raywave.cli.errors import CommandError, json_dumps

    assert json.loads(json_dumps({"bfl": math.inf, "x": [1.0, -math.inf]})) == {"bfl": "inf", "x": [1.0, "-inf"]}
    with pytest.raises(CommandError, match=r"a\.b is NaN"):
        json_dumps({"a": {"b": float("nan")}})


# ------------------------------------------------------------------ CLI arguments
def _cli(argv) -> tuple[int, str]:
    """Run the CLI in-process: (exit status, stderr). argparse's own usage errors exit 2 as well."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            rc = main(argv)
        except SystemExit as e:  # argparse: usage + one error line, status 2
            rc = e.code
    return rc, err.getvalue()


def _cli_bases(tmp: Path) -> dict:
    from PIL import Image

    img = tmp / "scene.png"
    Image.fromarray(np.full((8, 8, 3), 128, dtype=np.uint8)).save(img)
    np.save(tmp / "ph.npy", np.random.default_rng(0).uniform(0, 6.28, (16, 16)))
    cheap = ["--ks", "8", "--rays", "8", "--doe-pitch", "0.05"]
    return {
        "psf": ["psf", "singlet"] + cheap + ["--field", "0", "1", "--wavelength", "0.55", "--depth", "1000",
                                           "--doe-distance", "50", "--sensor-pitch", "0.01", "--oversample", "1"],
        "psfmap": ["psfmap", "singlet"] + cheap + ["--grid", "1", "--depths", "inf", "--wavelengths", "0.55"],
        "render": ["render", "singlet", str(img), "-o", str(tmp / "out.png")] + cheap + ["--grid", "1", "--depth",
                                                                                          "inf", "--wavelengths",
                                                                                          "0.55"],
        "info": ["info", "singlet", "--wavelength", "0.55", "--json"],
        "spot": ["spot", "singlet", "--fields", "0,1", "--json"],
        "doe": ["doe", "export", str(tmp / "ph.npy"), "--pitch", "0.001", "--levels", "4", "--wavelength", "0.55",
                "-o", str(tmp / "masks"), "--no-png"],
    }


def _cli_cases(tmp: Path, seed: int, n: int):
    rng = random.Random(seed)
    bases = _cli_bases(tmp)
    out = []
    for _ in range(n):
        name = rng.choice(sorted(bases))
        argv = list(bases[name])
        opts = [i for i, a in enumerate(argv) if a.startswith("--") and i + 1 < len(argv)
                and not argv[i + 1].startswith("-")]
        i = rng.choice(opts) + 1
        argv[i] = rng.choice(NASTY_TOKENS)
        if rng.random() < 0.2:
            argv.insert(rng.randrange(1, len(argv) + 1), rng.choice(["--bogus", "-x", "--ks", "nan"]))
        out.append(argv)
    return out


def _run_cli(tmp: Path, seeds, n: int) -> dict:
    counts = {"ok": 0, "refused": 0}
    for seed in seeds:
        for argv in _cli_cases(tmp, seed, n):
            rc, err = _cli(argv)
            assert "Traceback" not in err, (argv, err)
            assert rc in (0, 2), (argv, rc, err)
            if rc == 2:
                # as a terminal shows it: a progress bar drawn after its delay is cleared by a carriage return
                lines = [ln.rsplit("\r", 1)[-1] for ln in err.split("\n") if ln.rsplit("\r", 1)[-1].strip()]
                assert lines and (lines[-1].startswith("raywave: error:") or "error:" in lines[-1]), (argv, err)
                if not err.startswith("usage:"):
                    assert len(lines) == 1, (argv, err)
            counts["ok" if rc == 0 else "refused"] += 1
    return counts


def test_fuzzed_cli_arguments_exit_0_or_2_with_one_line(tmp_path):
    counts = _run_cli(tmp_path, range(2), 25)
    print(f"\nfuzzed CLI calls: {counts}")
    assert counts["refused"] > 25


@pytest.mark.slow
def test_many_fuzzed_cli_arguments(tmp_path):
    counts = _run_cli(tmp_path, range(100, 110), 60)
    print(f"\nfuzzed CLI calls (slow): {counts}")


# ------------------------------------------------------------------ training configs
def _train_cases(tmp: Path, seed: int, n: int):
    import yaml

    rng = random.Random(seed)
    base = yaml.safe_load(Path("configs/aberration_demo.yaml").read_text()) if Path("configs").exists() else {}
    if not base:
        base = yaml.safe_load((Path(__file__).resolve().parent.parent / "configs" / "aberration_demo.yaml").read_text())
    out = []
    for i in range(n):
        cfg = _mutate_json(base, rng)
        p = tmp / f"cfg{seed}_{i}.yaml"
        p.write_text(yaml.safe_dump(cfg) if rng.random() < 0.9 else yaml.safe_dump(cfg)[: rng.randrange(40)])
        out.append(p)
    return out


class _Reached(Exception):
    pass


def _run_train(tmp: Path, seeds, n: int, monkeypatch) -> dict:
    import raywave.training.trainer as tr

    def stop(*a, **k):
        raise _Reached

    monkeypatch.setattr(tr.Trainer, "__init__", stop)
    counts = {"accepted": 0, "refused": 0}
    for seed in seeds:
        for p in _train_cases(tmp, seed, n):
            run = tmp / f"run_{p.stem}"
            try:
                rc, err = _cli(["train", str(p), "-o", str(run), "--quiet"])
            except _Reached:
                counts["accepted"] += 1
                continue
            assert rc == 2 and "Traceback" not in err and err.count("\n") == 1, (p.read_text(), rc, err)
            assert not run.exists(), "the run folder was written before the config was refused"
            counts["refused"] += 1
    return counts


def test_fuzzed_training_configs_are_validated_before_the_run_folder(tmp_path, monkeypatch):
    counts = _run_train(tmp_path, range(3), 40, monkeypatch)
    print(f"\nfuzzed training configs: {counts}")
    assert counts["refused"] > 40


@pytest.mark.slow
def test_many_fuzzed_training_configs(tmp_path, monkeypatch):
    counts = _run_train(tmp_path, range(100, 120), 50, monkeypatch)
    print(f"\nfuzzed training configs (slow): {counts}")


@pytest.mark.parametrize("text,match", [
    ("stage1:\n  batch_size: 0\n", r"stage1\.batch_size must be >= 1"),
    ("checkpoint_every: 0\n", r"checkpoint_every must be >= 1"),
    ("stage1:\n  epochs: -1\n", r"stage1\.epochs must be >= 0"),
    ("pre_stage:\n  steps: -4\n", r"pre_stage\.steps must be >= 0"),
    ("stage1:\n  lr_doe: .nan\n", r"stage1\.lr_doe must be a finite number"),
    ("stage2:\n  lr_network: .inf\n", r"stage2\.lr_network must be a finite number"),
    ("", r"the config file is empty"),
    ("optics:\n  grid: [0, 3]\n", r"optics\.grid\[0\] must be >= 1"),
    ("optics:\n  ks: 2.5\n", r"optics\.ks must be an integer"),
])
def test_training_config_examples_are_refused_before_the_run(tmp_path, text, match):
    from raywave.training.config import ConfigError, load_config

    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_config(p)
    run = tmp_path / "run"
    rc, err = _cli(["train", str(p), "-o", str(run)])
    assert rc == 2 and "c.yaml" in err and not run.exists()


def test_every_numeric_training_setting_has_a_rule():
    """A new int / float / list setting must say its range (raywave.training.config.RULES)."""
    import dataclasses
    import typing

    from raywave.training import config as c

    missing = []
    for cls in (c.LensConfig, c.OpticsConfig, c.DataConfig, c.NetworkConfig, c.PreStageConfig, c.StageConfig,
                c.TrainConfig):
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            tp = hints[f.name]
            args = typing.get_args(tp) or (tp,)
            if any(a in (int, float, list, dict) or typing.get_origin(a) in (list, dict) for a in args):
                if f"{cls.__name__}.{f.name}" not in c.RULES:
                    missing.append(f"{cls.__name__}.{f.name}")
    assert not missing, missing


def test_a_stop_far_larger_than_the_beam_is_refused_not_traced_until_memory_runs_out(tmp_path):
    """Found by the slow fuzzing (seed 111): the bundled hybrid with its stop's radius set to 1e12 mm loaded, and its
    PSF then built a 3025×3025 node grid (the exit-pupil edge's ripple band around a degenerate footprint) and
    took 18 GB before dying. The node grid is now capped (MAX_NODE_RAYS) with an error naming the margin."""
    from raywave.hybrid.build import load_hybrid

    spec = json.loads((BUNDLED / "hybrid_asphere.json").read_text())
    spec["surfaces"][0]["aperture"]["radius"] = 1e12
    path = tmp_path / "huge_stop.json"
    path.write_text(json.dumps(spec))
    hl = load_hybrid(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ValueError, match=r"node grid would be \d+×\d+ rays .*stop_edge='doe'"):
            hl.psf((0.0, 0.0), ks=8, rays=8)
