"""open3d and trimesh are imported when a stage computes, not when the pipeline is loaded."""

import json
import subprocess
import sys

import numpy as np

from facecap_core.lazy import LazyModule

LOADED = """
import json, sys
import facecap.cli, facecap.flows.capture, facecap.flows.dataset
print(json.dumps({m: m in sys.modules for m in ("open3d", "trimesh")}))
"""


def test_loading_the_flows_imports_neither_open3d_nor_trimesh():
    """What a rerun whose every artifact is stored imports: the command line, the flows and
    every stage's module (to compute the keys). open3d and trimesh take 2-3 s of it."""
    done = subprocess.run([sys.executable, "-c", LOADED], capture_output=True, text=True,
                          timeout=300, check=True)
    assert json.loads(done.stdout.strip().splitlines()[-1]) == {"open3d": False,
                                                               "trimesh": False}


def test_a_lazy_module_is_the_module_from_its_first_use():
    import trimesh

    lazy = LazyModule("trimesh")
    assert "not loaded" in repr(lazy)
    box = lazy.creation.box()
    assert isinstance(box, lazy.Trimesh) and isinstance(box, trimesh.Trimesh)
    assert lazy.Trimesh is trimesh.Trimesh and "loaded" in repr(lazy)


def test_no_hit_is_open3d_s_invalid_id():
    import open3d as o3d

    from facecap_core.render import NO_HIT

    assert NO_HIT == np.uint32(o3d.t.geometry.RaycastingScene.INVALID_ID)


def test_ply_vertices_reads_what_open3d_and_trimesh_write(tmp_path):
    """The page reads the fusion's cloud and the fitting's mesh without open3d or trimesh:
    the same numbers as those libraries read; any other PLY is left to them (None)."""
    import open3d as o3d
    import trimesh

    from facecap_core.meshio import ply_vertices
    from facecap_core.mvs.fusion import PointCloud, write_ply

    rng = np.random.default_rng(0)
    points = rng.normal(size=(500, 3)) * 80
    colours = rng.integers(0, 256, size=(500, 3), dtype=np.uint8)
    cloud = PointCloud(points, rng.normal(size=(500, 3)), colours, np.full(500, 3.0),
                       np.full(500, 0.2))
    write_ply(cloud, tmp_path / "cloud.ply")
    got = ply_vertices(tmp_path / "cloud.ply")
    read = o3d.io.read_point_cloud(str(tmp_path / "cloud.ply"))
    assert np.array_equal(np.stack([got[k] for k in "xyz"], 1), np.asarray(read.points))
    assert np.array_equal(np.stack([got[k] for k in ("red", "green", "blue")], 1), colours)

    box = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    box.visual.vertex_colors = rng.integers(0, 256, size=(len(box.vertices), 4))
    box.export(tmp_path / "mesh.ply")
    got = ply_vertices(tmp_path / "mesh.ply")
    again = trimesh.load(tmp_path / "mesh.ply", process=False)
    assert np.array_equal(np.stack([got[k] for k in "xyz"], 1), again.vertices)

    box.export(tmp_path / "ascii.ply", encoding="ascii")
    assert ply_vertices(tmp_path / "ascii.ply") is None
    (tmp_path / "faces_first.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement face 1\n"
        b"property list uchar int vertex_indices\nelement vertex 3\nproperty float x\n"
        b"end_header\n")
    assert ply_vertices(tmp_path / "faces_first.ply") is None
    (tmp_path / "not.ply").write_bytes(b"solid mesh\n")
    assert ply_vertices(tmp_path / "not.ply") is None


def test_a_lazy_module_does_not_answer_for_dunders_nor_load_for_them():
    import copy

    lazy = LazyModule("json")
    assert not hasattr(lazy, "__wrapped__") and "not loaded" in repr(lazy)
    assert copy.copy(lazy)._name == "json"
