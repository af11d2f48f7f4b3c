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
