"""Architecture guards (cf. prysm): physics never imports plotting, matplotlib or the CLI, and importing
raywave does not change torch's global state."""

import subprocess
import sys

PHYSICS = ["raywave.materials", "raywave.surfaces", "raywave.rays", "raywave.lens", "raywave.io", "raywave.doe",
           "raywave.doe.fabrication", "raywave.doe.tolerance", "raywave.wave", "raywave.hybrid", "raywave.hybrid.build",
           "raywave.hybrid.metrics",
           "raywave.models", "raywave.models.interface", "raywave.models.paraxial", "raywave.models.pupil",
           "raywave.models.local_grating",
           "raywave.imaging", "raywave.imaging.psfmap", "raywave.imaging.render", "raywave.imaging.sensor",
           "raywave.imaging.color",
           "raywave.imaging.data", "raywave.training.networks", "raywave.training.replay", "raywave.training.config",
           "raywave.training.schedule", "raywave.training.losses", "raywave.training.metrics", "raywave.training.checkpoint",
           "raywave.training.trainer", "raywave.training.distributed",
           "raywave.training.baselines", "raywave.training.parallel"]


def _modules_after_import(mods):
    code = "import sys\n" + "".join(f"import {m}\n" for m in mods) + "print('\\n'.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_physics_does_not_import_plotting_or_cli():
    loaded = _modules_after_import(PHYSICS)
    assert "matplotlib" not in loaded
    assert not any(m.startswith("raywave.plotting") or m.startswith("raywave.cli") for m in loaded)


def test_io_does_not_import_torch():
    loaded = _modules_after_import(["raywave.io"])
    assert "torch" not in loaded


def test_import_leaves_torch_defaults_alone():
    code = (
        "import torch; d = torch.get_default_dtype(); import raywave, raywave.lens.lens, raywave.materials;"
        "from raywave.lens.build import load_lens; assert torch.get_default_dtype() == d == torch.float32"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
