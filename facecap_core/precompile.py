"""Compile the numba kernels into numba's on-disk cache, so that a capture does not.

Compiling them takes about 40 s of CPU; ``@numba.njit(cache=True)`` keeps the machine code in
``__pycache__`` beside each source file (``*.nbi`` index, ``*.nbc`` code), keyed by the exact
argument types. ``make install`` and the worker image run this module once; the first
capture then loads every kernel from the cache instead of compiling it.

The signatures are the argument types the pipeline passes (C-contiguous, writable arrays).
Compiling by signature needs no valid inputs; a call with other types (float64 for float32,
a strided view) would compile again at run time, which ``NUMBA_DEBUG_CACHE=1`` shows and
tests/test_precompile.py checks for the kernels' callers. The kernels these call (the PBA
pixel model, the PatchMatch cost functions) are compiled and cached with them.

    python -m facecap_core.precompile
"""

from __future__ import annotations

import sys
import time

from numba import types as nt

# Array types by dimension count, all C-contiguous as the callers make them.
I32_1, I32_2 = nt.int32[::1], nt.int32[:, ::1]
I64_1, I64_2 = nt.int64[::1], nt.int64[:, ::1]
F32_1, F32_2, F32_3 = nt.float32[::1], nt.float32[:, ::1], nt.float32[:, :, ::1]
F64_1, F64_2 = nt.float64[::1], nt.float64[:, ::1]
F64_3, F64_4 = nt.float64[:, :, ::1], nt.float64[:, :, :, ::1]
BOOL_1 = nt.boolean[::1]
IMAGES = nt.ListType(F32_2)  # numba.typed.List of float32 images (PBA's pyramid level)
F64, I64, BOOL = nt.float64, nt.int64, nt.boolean


def _patchmatch_signature() -> tuple:
    """facecap_core.mvs.patchmatch.patchmatch_depth's call of ``_patchmatch``."""
    return (I32_1, I32_1, I32_2, BOOL_1, F32_2, F32_2, F32_2, F32_3, BOOL,  # .. use_prior
            F32_3, F64_3, F64_2, F64, F64, F64, F64,  # srcs, A, b, fx, fy, cx, cy
            F32_1, F32_1, F32_2, F32_2, I64, I64, I64, I32_2, I64, F64, I64, I64,  # .. pixel_views
            F32_2, F32_3, F32_2)  # depth, normal, cost


def _normal_ray_signature() -> tuple:
    """facecap_core.nonrigid.constraints.cloud_targets's call of ``_normal_ray_kernel``."""
    return (F64_2, F64_2, F64_2, F64_2, F64_1, F64_1, F64, I64_1, I64_1, F64, F64, F64, I64)


def _accumulate_signature() -> tuple:
    """facecap_core.pose.pba.normal.accumulate_in_chunks's call of ``accumulate``."""
    return (I64_1, F64_2, F64_1, I64_1, I64_1, IMAGES, IMAGES, IMAGES,  # .. grad_y
            F64_2, F64_2, I64, F64_2, F64, I64,  # host_weights .. rows
            F64_4, F64_3, F64_2, F64_1, F64, F64, BOOL, BOOL,  # R_rel .. jacobians
            F64_2, F64_1, F64_1, F64_1, F64_2, I64_2, F64_1, F64_1)  # H .. res_out


def _accumulate_tracks_signature() -> tuple:
    """facecap_core.pose.pba's calls of ``accumulate_tracks`` (solve.py and normal.py)."""
    return (F64_2, I64_1, I64_1, F64_2, F64_3, F64_2, F64_1, F64, F64,  # X .. huber_px
            F64_2, F64, I64, BOOL,  # velocity .. with_cameras
            F64_2, F64_1, F64_3, F64_2, F64_3, F64_1)  # H .. stats


def _search_depth_signature() -> tuple:
    """facecap_core.pose.pba.problem's call of ``search_depth``."""
    return (I64_1, F64_2, F64_2, F64, F64, I64, I64, IMAGES, F64_4, F64_3,
            F64_1, F64_1, F64_1)


def _patch_scores_signature() -> tuple:
    """facecap_core.nonrigid.photometric._measure's call of ``_patch_scores``."""
    return (F64_3, F64_2, I64_2, F64_1, F32_3, F64_3, F64_2, F64_2, I64_1, F64_2)


def _sweep_signature() -> tuple:
    """facecap_core.measure.straighten's call of ``_sweep``."""
    return (F64_2, F64_2, F64_1, BOOL_1, I64)


def _patch_points_signature() -> tuple:
    """facecap_core.nonrigid.photometric._measure's call of ``_patch_points``."""
    return (F64_2, F64_2, F64_2, F64_2, F64_2, F64_1, F64_1, F64_1)


def _blend_view_signature() -> tuple:
    """facecap_core.texture.bake_texture's call of ``_blend_view``."""
    return (I64_1, F64_1, F64_1, F32_2, F64_1, F64_2, F64_1)


def kernels() -> list[tuple[str, object, tuple]]:
    """(name, dispatcher, signature) of every kernel the pipeline calls from Python."""
    # Imported when asked for: each stage module loads numba and compiles nothing until
    # called, but the command line's --help must not load the stages.
    from facecap_core import measure, texture
    from facecap_core.mvs import patchmatch
    from facecap_core.nonrigid import constraints, photometric
    from facecap_core.pose.pba import kernels as pba_kernels
    from facecap_core.pose.pba import normal, problem

    return [
        ("measure._sweep", measure._sweep, _sweep_signature()),
        ("mvs.patchmatch._patchmatch", patchmatch._patchmatch, _patchmatch_signature()),
        ("texture._blend_view", texture._blend_view, _blend_view_signature()),
        ("nonrigid.constraints._normal_ray_kernel", constraints._normal_ray_kernel,
         _normal_ray_signature()),
        ("nonrigid.photometric._patch_scores", photometric._patch_scores,
         _patch_scores_signature()),
        ("nonrigid.photometric._patch_points", photometric._patch_points,
         _patch_points_signature()),
        ("pose.pba.kernels.accumulate", pba_kernels.accumulate, _accumulate_signature()),
        ("pose.pba.normal.accumulate_tracks", normal.accumulate_tracks,
         _accumulate_tracks_signature()),
        ("pose.pba.problem.search_depth", problem.search_depth, _search_depth_signature()),
    ]


def compile_kernels(log=print) -> dict[str, str]:
    """Compile (or load from the cache) every kernel; per kernel, "compiled" or "cached"."""
    done = {}
    for name, dispatcher, signature in kernels():
        start = time.perf_counter()
        misses = sum(dispatcher.stats.cache_misses.values())
        dispatcher.compile(signature)
        compiled = sum(dispatcher.stats.cache_misses.values()) > misses
        done[name] = "compiled" if compiled else "cached"
        log(f"  {name}: {done[name]} ({time.perf_counter() - start:.1f} s)")
    return done


def main() -> int:
    print("compiling the numba kernels into their cache")
    compile_kernels()
    return 0


if __name__ == "__main__":
    sys.exit(main())
