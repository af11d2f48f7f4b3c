"""Build the trimmed ICT Face Model that ships in the package.

    python tools/trim_ict_model.py [--source ../shared/data/ict_face_model/ict_face_model.npz]
                                   [--modes 30] [--out facecap_core/data/ict_face_model_trimmed.npz]

From the ICT Face Model Light npz (MIT, USC ICT; see facecap_core/data/README.md) it keeps
only what facecap reads (``facecap_core/template.py`` and ``facecap/synthetic/``):

* the vertices of the skin (face + head and neck, 0-11247), the mouth and eye sockets
  (11248-14061) and the eyeballs (sclera and iris, 21451-24590), renumbered in their original
  order: skin and socket vertices keep their indices, the eyeballs move down to 14062-17201;
* the triangles of the materials M_Face, M_BackHead and the sclera / iris materials, in their
  original order, with their material index (``material_names`` is unchanged);
* the first ``--modes`` identity modes, in float16 (cm; the largest value is 1.33 cm, so the
  rounding is under 0.0005 cm = 5 µm), and the mean mesh in float32;
* ``landmarks68`` (all on the skin, indices unchanged);
* ``source_vertex_ids``: the index in the full model of every kept vertex.

Teeth, gums, tear film, eye blend / occlusion shells, eyelashes, UVs and the region tables
are dropped. The zip is written with fixed timestamps, so the same source and arguments give
the same bytes (the sha256 is printed).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import os
import zipfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SOURCE = ROOT.parent / "shared" / "data" / "ict_face_model" / "ict_face_model.npz"
DEFAULT_OUT = ROOT / "facecap_core" / "data" / "ict_face_model_trimmed.npz"

KEPT_MATERIALS = ("M_Face", "M_BackHead", "M_ScleraLeft", "M_IrisLeft", "M_ScleraRight",
                  "M_IrisRight")
KEPT_VERTEX_RANGES = ((0, 14061), (21451, 24590))  # inclusive: skin + sockets, eyeballs


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def trim(model: dict, modes: int) -> dict[str, np.ndarray]:
    n = len(model["mean_vertices"])
    keep = np.zeros(n, bool)
    for first, last in KEPT_VERTEX_RANGES:
        keep[first:last + 1] = True
    names = [str(s) for s in model["material_names"]]
    material_ids = [names.index(m) for m in KEPT_MATERIALS]
    face_keep = np.isin(model["face_material"], material_ids)
    faces = model["faces"][face_keep]
    if not keep[faces].all():
        raise SystemExit("a kept triangle uses a dropped vertex: not the expected ICT model")
    if not keep[model["landmarks68"]].all():
        raise SystemExit("a landmark lies on a dropped vertex: not the expected ICT model")
    if modes > len(model["identity_basis"]):
        raise SystemExit(f"the source has only {len(model['identity_basis'])} identity modes")
    remap = np.full(n, -1, np.int64)
    remap[keep] = np.arange(keep.sum())
    return {
        "mean_vertices": model["mean_vertices"][keep].astype(np.float32),
        "identity_basis": model["identity_basis"][:modes, keep].astype(np.float16),
        "faces": remap[faces].astype(np.int32),
        "face_material": model["face_material"][face_keep].astype(np.int8),
        "material_names": model["material_names"],
        "landmarks68": remap[model["landmarks68"]].astype(np.int32),
        "source_vertex_ids": np.flatnonzero(keep).astype(np.int32),
        "units": model["units"],
    }


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """An npz (np.load reads it) with fixed timestamps: reproducible bytes."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as z:
        for key, array in arrays.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.asarray(array), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            z.writestr(info, buffer.getvalue(), compresslevel=9)
    os.replace(tmp, path)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("--source", type=Path,
                    default=Path(os.environ.get("FACECAP_ICT_MODEL") or DEFAULT_SOURCE))
    ap.add_argument("--modes", type=int, default=30)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    with np.load(args.source, allow_pickle=False) as z:
        model = {k: z[k] for k in z.files}
    trimmed = trim(model, args.modes)
    write_npz(args.out, trimmed)
    # What the trimming costs: the dropped modes' displacement of the skin (1 sigma each).
    skin = slice(0, 11248)
    dropped = model["identity_basis"][args.modes:, skin].astype(np.float64)
    rms = 10 * np.sqrt((dropped ** 2).sum(axis=(0, 2)))
    kept = model["identity_basis"][:args.modes, skin].astype(np.float64)
    rounding = 10 * np.abs(trimmed["identity_basis"][:, :11248].astype(np.float64) - kept).max()
    print(f"source {args.source} sha256 {sha256(args.source)}")
    print(f"wrote {args.out}: {args.out.stat().st_size:,} bytes, sha256 {sha256(args.out)}")
    print(f"{len(trimmed['mean_vertices'])} of {len(model['mean_vertices'])} vertices, "
          f"{len(trimmed['faces'])} of {len(model['faces'])} triangles, "
          f"{args.modes} of {len(model['identity_basis'])} identity modes")
    print(f"dropped modes move a skin vertex by {rms.mean():.2f} mm rms on average "
          f"(max {rms.max():.2f} mm) for N(0,1) coefficients; float16 rounding of the kept "
          f"modes at most {rounding * 1000:.1f} µm")


if __name__ == "__main__":
    main()
