"""The numba kernels compiled ahead (facecap_core.precompile) are what a run loads."""

import json
import os
import subprocess
import sys

import pytest

from facecap_core.precompile import kernels


def test_every_kernel_is_cached_on_disk():
    """A kernel without ``cache=True`` would compile in every process, precompiled or not."""
    for name, dispatcher, _ in kernels():
        assert dispatcher._cache.__class__.__name__ != "NullCache", name


def _python(code: str, cache_dir) -> dict:
    """Run ``code`` in a fresh interpreter with numba's cache in ``cache_dir``; its last line
    of output, JSON."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=900, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


# The real caller of the point-cloud kernel, on a tiny cloud: the types it passes are the
# pipeline's, so a precompiled signature that differs from them shows as a cache miss.
CLOUD_TARGETS = """
import json
import numpy as np
from facecap_core.nonrigid.constraints import CloudGrid, _normal_ray_kernel, cloud_targets
rng = np.random.default_rng(0)
grid = CloudGrid.build(rng.normal(size=(50, 3)), None, 1.0)
cloud_targets(rng.normal(size=(20, 3)), np.tile([0.0, 0.0, 1.0], (20, 1)), grid, 1.0, 0.5)
stats = _normal_ray_kernel.stats
print(json.dumps({"hits": sum(stats.cache_hits.values()),
                  "misses": sum(stats.cache_misses.values())}))
"""


@pytest.mark.slow
def test_a_fresh_process_loads_the_precompiled_kernels(tmp_path):
    first = _python("import json; from facecap_core.precompile import compile_kernels; "
                    "print(json.dumps(compile_kernels(log=lambda line: None)))", tmp_path)
    assert set(first.values()) == {"compiled"}
    again = _python("import json; from facecap_core.precompile import compile_kernels; "
                    "print(json.dumps(compile_kernels(log=lambda line: None)))", tmp_path)
    assert set(again.values()) == {"cached"}
    called = _python(CLOUD_TARGETS, tmp_path)
    assert called == {"hits": 1, "misses": 0}
