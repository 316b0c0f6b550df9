"""Does the README's own-mesh recipe end in a verdict, and beat the closed-form baseline, on a
mesh nobody tuned forcecal on?

The mesh is SOFA's liver (``share/mesh/liver.msh`` of sofa-framework/sofa at :data:`COMMIT`:
181 vertices, 596 tets, Gmsh's legacy format 1; LGPL-2.1, so not kept here), the mesh of
SOFA's liver demos, kept out of the corpus for this check. The scene,
``scenes/independent/sofa_liver.toml``, is the README's "Running your own mesh" recipe as a new
user would run it: copied, then changed only where a message said so (its comments say which
message).

``python -m studies.independent_check --sofa GIT_DIR [--run DIR] [--out JSON]`` writes the
mesh from the SOFA repository (``GIT_DIR``: its git directory, any clone holding the commit;
checked against :data:`SHA256`) unless it is there, runs ``python -m pipelines demo`` on the
scene into ``--run`` (default ``runs/studies/independent_check_sofa_liver/``; a finished run
is reused stage by stage) and records what the run's ``report.json`` says: the verdict, each
check's calibrated and baseline errors and goal, the FE's failures and replacements, the
whole-body data the fit used and why any asked-for kind was left out, the stage times. Without
``--sofa`` the mesh must be there already. About 15 min on 2 cores.
"""

from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "independent" / "sofa_liver.toml"
MESH = SCENE.parent / "meshes" / "liver.msh"
REPOSITORY = "sofa-framework/sofa"
COMMIT = "2a278d891fe68ae5a835259bd62a2844df1670a1"
SOURCE = "share/mesh/liver.msh"
SHA256 = "220e9e2dc51fe511cd185a29085f3fc373d258e613c3e86d86c790268d9c8ed5"
RUN = ROOT / "runs" / "studies" / "independent_check_sofa_liver"
OUT = ROOT / "runs" / "studies" / "independent_check_sofa_liver.json"


def write_mesh(git_dir: Path) -> None:
    """:data:`SOURCE` at :data:`COMMIT` of the repository in ``git_dir`` to :data:`MESH`,
    refused unless its SHA-256 is :data:`SHA256`."""
    done = subprocess.run(["git", "--git-dir", str(git_dir), "show", f"{COMMIT}:{SOURCE}"],
                          capture_output=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"error: {git_dir}: cannot read {SOURCE} at {COMMIT}: "
                         f"{done.stderr.decode(errors='replace').strip()}")
    digest = hashlib.sha256(done.stdout).hexdigest()
    if digest != SHA256:
        raise SystemExit(f"error: {SOURCE} at {COMMIT} has SHA-256 {digest}, expected {SHA256}")
    MESH.parent.mkdir(parents=True, exist_ok=True)
    tmp = MESH.with_suffix(".msh.tmp")
    tmp.write_bytes(done.stdout)
    tmp.replace(MESH)


def summary(report: dict[str, Any]) -> dict[str, Any]:
    """What a ``report.json`` says about the run (module docstring)."""
    verdict = report.get("verdict") or {}
    body = report.get("body") or {}
    return {
        "passed": verdict.get("passed"),
        "checks": {name: {key: check.get(key) for key in
                          ("status", "calibrated", "baseline", "goal", "reason")}
                   for name, check in (verdict.get("checks") or {}).items()},
        "fe_failures": report.get("fe_failures"),
        "failures": report.get("failures"),
        "body": {key: body.get(key) for key in ("status", "kinds", "weight", "failure")},
        "mesh": report.get("mesh"),
        "timings_s": report.get("timings_s"),
        "realtime": report.get("realtime"),
    }


def run(run_dir: Path) -> dict[str, Any]:
    """Run the pipeline on :data:`SCENE` into ``run_dir``; its :func:`summary` with the exit
    status (and the last line it printed when it wrote no report)."""
    from pipelines.report import read_report

    done = subprocess.run([sys.executable, "-m", "pipelines", "demo", "--scene", str(SCENE),
                           "--out", str(run_dir), "--no-progress"], cwd=ROOT,
                          capture_output=True, text=True, check=False)
    report_path = run_dir / "report.json"
    out: dict[str, Any] = {"exit_status": done.returncode}
    if report_path.is_file():
        out.update(summary(read_report(report_path)))
    else:
        lines = (done.stderr or done.stdout).strip().splitlines()
        out["error"] = lines[-1] if lines else None
    return out


def main(argv: list[str] | None = None) -> int:
    from studies.viscoelastic_volume import write_json

    ap = argparse.ArgumentParser(prog="python -m studies.independent_check",
                                 description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--sofa", type=Path, help="git directory of a sofa-framework/sofa clone "
                    "holding the pinned commit (writes the mesh)")
    ap.add_argument("--run", type=Path, default=RUN, help="the pipeline's output folder")
    ap.add_argument("--out", type=Path, default=OUT, help="the result (JSON)")
    args = ap.parse_args(argv)
    if args.sofa is not None:
        write_mesh(args.sofa)
    if not MESH.is_file():
        raise SystemExit(f"error: {MESH} is missing: give --sofa <git dir of {REPOSITORY}>")
    result = {"scene": SCENE.stem, "source": {"repository": REPOSITORY, "commit": COMMIT,
                                              "path": SOURCE, "sha256": SHA256},
              "command": "python -m studies.independent_check --sofa <git dir of "
                         f"{REPOSITORY}>", **run(args.run)}
    write_json(args.out, result)
    print(f"wrote {args.out}: verdict {'passed' if result.get('passed') else 'failed'}, "
          f"exit status {result['exit_status']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
