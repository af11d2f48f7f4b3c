"""Make ``facecap_core/data/template_uv.npz``: the default template's texture coordinates.

The fitted mesh keeps the template's topology, so one UV layout, made once, serves every
fit: texel (u, v) is the same point of the skin on every face. The layout is xatlas's
(``pip install xatlas``, MIT; needed by this script only, never at run time) on the
template's rest shape: charts cut along the seams xatlas chooses, packed into a square with
``--padding`` texels between charts at ``--resolution``.

The file holds (read by :func:`facecap_core.texture.template_uv`):

* ``uv``: float32 (M, 2), OBJ convention (origin bottom-left, v up), in [0, 1];
* ``vertex``: int32 (M,), the template vertex of each UV vertex. The first N rows are the
  template's vertices in order (``vertex[:N] == arange(N)``); the rows after them are the
  copies of vertices on a seam, so a mesh split at the seams (glTF) starts with the
  template's own vertices;
* ``faces``: int32 (F, 3), each template triangle's corners as rows of ``uv``, in the
  template's face order;
* ``template_faces_sha256``: the digest of the template's faces (int64, C order), so a
  different template is never given these UVs.

Made by: ``.venv/bin/python tools/make_template_uv.py`` (xatlas 0.0.11, default options
but the padding and resolution below).
"""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parents[1] / "facecap_core" / "data" / "template_uv.npz"


def faces_digest(faces: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(faces, np.int64).tobytes()).hexdigest()


def unwrap(vertices: np.ndarray, faces: np.ndarray, resolution: int, padding: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(uv, vertex, faces) as the file stores them (see the module's docstring)."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(np.asarray(vertices, np.float32), np.asarray(faces, np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution, pack.padding, pack.bilinear = resolution, padding, True
    atlas.generate(xatlas.ChartOptions(), pack)
    vmapping, indices, uvs = atlas[0]
    n = len(vertices)
    # Template vertices first, in order: each one's first UV copy takes row i.
    first = np.full(n, -1, np.int64)
    order = np.arange(len(vmapping))[::-1]
    first[vmapping[order]] = order  # the last write per vertex is its lowest copy
    copies = np.setdiff1d(np.arange(len(vmapping)), first[first >= 0])
    row = np.empty(len(vmapping), np.int64)
    row[first[first >= 0]] = np.flatnonzero(first >= 0)
    row[copies] = n + np.arange(len(copies))
    uv = np.zeros((n + len(copies), 2), np.float32)
    uv[row] = uvs
    vertex = np.concatenate([np.arange(n), vmapping[copies]]).astype(np.int32)
    return uv, vertex, row[indices].astype(np.int32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--resolution", type=int, default=1024)
    parser.add_argument("--padding", type=int, default=4)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    from facecap_core.template import Template

    template = Template.default()
    uv, vertex, faces = unwrap(template.vertices, template.faces, args.resolution, args.padding)
    np.savez_compressed(args.out, uv=uv, vertex=vertex, faces=faces,
                        template_faces_sha256=faces_digest(template.faces))
    print(f"{args.out}: {len(uv)} UV vertices ({len(uv) - len(template.vertices)} seam "
          f"copies), {len(faces)} faces, {args.out.stat().st_size} bytes")


if __name__ == "__main__":
    main()
