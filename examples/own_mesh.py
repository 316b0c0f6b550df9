"""Your own mesh from scratch: a mesh file, a scene file, every stage, the calibrated model.

A 6 x 6 x 3 cm block (48 vertices, 108 tets) stands in for your organ: it is written as a
VTU file in millimetres, the way a mesher exports one (any tetrahedral mesh meshio reads
works: .msh, .vtu, .vtk, .xdmf). A scene file next to it says how to read it (``mesh.scale``),
which side rests on the support (``fixed``), the tissue's material and what to compute, on
tiny settings (9 calibration points, short relaxation and gravity runs, the global fit and
one sweep of local tuning) so the whole run takes seconds. Then the four stages run (as
``python -m pipelines demo --scene <out>/block.toml --out <out>/run`` does), and the
calibrated model is loaded from the run's ``params.h5`` and its errors printed.

    python examples/own_mesh.py --out runs/examples/own_mesh
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import meshio

import forcecal
from forcecal.mesh import box_mesh
from forcecal.scene import load_scene
from pipelines.stages import run_pipeline

SCENE = """\
name = "block"
description = "a 6 x 6 x 3 cm block resting on its base, tiny settings"

[mesh]
source = "block.vtu"
scale = 0.001            # the file is in mm

[fixed]
axis = "z"               # the base (lowest z) rests on the support
side = "min"

[material]               # Mooney-Rivlin + 2-term Prony, SI units
C10 = 2000.0
C01 = 1000.0
kappa = 300000.0
density = 1060.0
prony_g = [0.35, 0.25]
prony_tau = [0.05, 0.2]

[test_points]
calibration = "auto"
n_calibration = 9
n_held_out = 8

[indentation]
depth = 0.003

[relaxation]
depth = 0.003
ramp_time = 0.1
ramp_steps = 2
hold_time = 1.0
hold_steps = 4

[gravity]
duration = 0.2
static_load_steps = 2

[calibration]
workers = 1
local_max_evaluations = 30
local_max_sweeps = 1

[particle]
volume = true           # springs + the per-tet volume term

[outputs]
figures = false
"""


def write_block(folder: Path) -> Path:
    """The block's mesh as ``block.vtu`` (mm) and its scene as ``block.toml``; the scene."""
    folder.mkdir(parents=True, exist_ok=True)
    mesh = box_mesh((3, 3, 2), (60.0, 60.0, 30.0))  # your mesher here, in its own units
    meshio.write(folder / "block.vtu", meshio.Mesh(mesh.vertices, [("tetra", mesh.tets)]))
    (folder / "block.toml").write_text(SCENE)
    return folder / "block.toml"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="runs/examples/own_mesh", help="output folder")
    parser.add_argument("--ranks", type=int, default=1,
                        help="MPI ranks of the FE reference (1: in this process)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    scene = load_scene(write_block(out))
    for outcome in run_pipeline(scene, out / "run", progress=False, ranks=args.ranks):
        print(f"{outcome.stage:<10} {'ran' if outcome.ran else 'skipped':<8} "
              f"{outcome.seconds:6.1f} s")
    report = json.loads((out / "run" / "report.json").read_text())
    model = forcecal.load_model(out / "run" / "params.h5")
    print(f"calibrated model: {model.n_particles} particles ({int(model.fixed.sum())} fixed), "
          f"{model.n_connectors} connectors, {model.masses.sum() * 1e3:.1f} g")
    print("relative RMS error      calibrated  baseline (Van Gelder)")
    for key in ("indentation_calibrated", "indentation_held_out", "relaxation_held_out",
                "gravity_static"):
        print(f"  {key:<22} {report['errors'][key]:9.3f} "
              f"{report['baseline_errors'][key]:9.3f}")
    return {"report": report, "model": model, "params": out / "run" / "params.h5"}


if __name__ == "__main__":
    main(sys.argv[1:])
