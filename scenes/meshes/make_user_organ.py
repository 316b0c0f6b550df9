"""Make ``user_organ.vtu``: an organ mesh as a user might bring it from another tool.

A kidney-like bean (one ellipsoidal lobe with a notch on one side and a flat
top where it hangs) -- deliberately *not* the shape of forcecal's generated
liver -- meshed with gmsh into about 500 vertices and written with meshio the
way meshes exported from other simulators often come: coordinates in
millimetres, y pointing up. ``scenes/user_organ.toml`` reads it with
``mesh.scale = 0.001``, fixes the vertices of the flat top (``y`` max) and
points gravity along -y.

gmsh runs single-threaded with a fixed seed, so rerunning the script rewrites
the same file (bit for bit with the same gmsh version)::

    .venv/bin/python scenes/meshes/make_user_organ.py
"""

from pathlib import Path

import meshio
import numpy as np

from forcecal.liver_mesh import gmsh_session, mesh_volume

OUT = Path(__file__).with_name("user_organ.vtu")
MESH_SIZE_MM = 13.0  # gives ~520 vertices, mean edge ~ 15 mm (the indentation depth is 5 mm)


def make(mesh_size_mm: float = MESH_SIZE_MM) -> meshio.Mesh:
    """The organ meshed with gmsh at target edge length ``mesh_size_mm`` [mm] (coordinates in mm)."""
    with gmsh_session("user_organ") as gmsh:
        occ = gmsh.model.occ
        # body: ellipsoid 170 x 110 x 80 mm (x along the long axis, y up)
        body = occ.addSphere(0.0, 0.0, 0.0, 1.0)
        occ.dilate([(3, body)], 0.0, 0.0, 0.0, 85.0, 55.0, 40.0)
        # the bean's notch (hilum): a vertical cylinder cut into the -z side
        notch = occ.addCylinder(10.0, -80.0, -55.0, 0.0, 160.0, 0.0, 30.0)
        cut, _ = occ.cut([(3, body)], [(3, notch)])
        # flat top where it hangs: everything above y = 42 mm removed
        top = occ.addBox(-100.0, 42.0, -100.0, 200.0, 100.0, 200.0)
        cut, _ = occ.cut(cut, [(3, top)])
        occ.synchronize()
        points, tets = mesh_volume(gmsh, mesh_size_mm)
    return meshio.Mesh(np.round(points, 6), [("tetra", tets)])


if __name__ == "__main__":
    mesh = make()
    meshio.write(OUT, mesh, binary=True)
    print(f"{OUT}: {len(mesh.points)} vertices, {len(mesh.cells[0].data)} tets")
