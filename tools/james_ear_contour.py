"""James's hand-labelled ground-truth ear contour (benchmarks/data/james_ear_contour.json).

    python tools/james_ear_contour.py render [--out DIR] [--overlay]
    python tools/james_ear_contour.py build [--traces FILE]
    python tools/james_ear_contour.py check [--out DIR]

The scan "james" has no ear geometry: his ears are texture on a flat, hair-covered surface.
This tool makes a 3D contour that follows the ear his texture shows, by hand:

* ``render``: renders the labelling views (4 per side, cameras stored in the JSON: yaw
  60-90 deg, elevation -10..15 deg, 720 x 720 px, ear about 250 px tall, fixed lights, no
  noise) and the check views into ``--out`` (default ``out/james_ear_contour``); with
  ``--overlay`` also enlarged crops with the labelled traces (red), the 12 points taken from
  them (green) and the stored 3D contour reprojected (magenta).
* ``build``: from the hand traces (one polyline per labelling view, helix root to the bottom
  of the lobe along the outer edge of the textured ear; ``--traces`` a JSON of
  ``{view: {"trace": [[u, v], ...]}}``, else the traces already in the file):
  1. each trace is cast onto the scan's surface (a ray per trace point, every 1 px); the
     side's two ends are the means of the views' cast end points (snapped to the scan); each
     view's cast trace, from its point nearest to the start to its point nearest to the end,
     is cut into 11 equal lengths measured in the head's side plane (y, z), the way the
     template's contour is spaced (docs/ears.md); the 12 cuts taken back to the image are
     that view's points, so that the same point number means the same place along the rim
     in every view;
  2. each point is triangulated from its views (linear DLT, then least squares on the
     reprojection error);
  3. the triangulated point is snapped to the scan (closest surface point; the distance is
     stored), and then moved on the surface to where its reprojection error over the views is
     least (the ear is a flat texture, so the true point is on the surface; the closest point
     is not the best one when the views look along the surface);
  4. writes the contour, the per-view points and reprojection errors, the snap distances and
     the spread of the single-view surface points (the labelling uncertainty).
* ``check``: renders the check views (not used for labelling) with the contour reprojected.

Head frame of ``make_subject(SynthConfig(subject="james"))``, mm: x = the subject's left,
y = up, z = forwards.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from facecap.synthetic import Renderer, Room, make_subject  # noqa: E402
from facecap.synthetic.config import SynthConfig  # noqa: E402
from facecap.synthetic.sensor import to_srgb8  # noqa: E402
from facecap_core.camera import Intrinsics, camera_center, look_at, pixel_rays  # noqa: E402
from facecap_core.render import RaycastScene  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "benchmarks/data/james_ear_contour.json"
SIDES = ("left", "right")
COUNT = 12


def intrinsics(view: dict) -> Intrinsics:
    return Intrinsics(view["width"], view["height"], view["fx"], view["fy"], view["cx"],
                      view["cy"])


def projection(view: dict) -> np.ndarray:
    K = intrinsics(view).K
    return K @ np.hstack([np.asarray(view["R"]), np.asarray(view["t"])[:, None]])


def project(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    x = np.c_[np.atleast_2d(X), np.ones(len(np.atleast_2d(X)))] @ P.T
    return x[:, :2] / x[:, 2:]


def render_view(subject, room, view: dict) -> np.ndarray:
    """The view's image (RGB uint8): fixed key and fill lights from the camera's side."""
    intr = intrinsics(view)
    R, t = np.asarray(view["R"]), np.asarray(view["t"])
    renderer = Renderer(subject, room, intr, [], 0.4, 0.0)
    renderer.rays = pixel_rays(intr)
    direction = np.asarray(view.get("light_direction", camera_center(R, t)), float)
    direction = direction / np.linalg.norm(direction)
    key = direction + [0.0, 0.6, 0.0]
    fill = direction + [0.0, -0.3, 0.5]
    renderer.lights = [(key / np.linalg.norm(key), 0.55), (fill / np.linalg.norm(fill), 0.2)]
    img, _ = renderer.render(R, t)
    return to_srgb8(img)


def cast_trace(scene: RaycastScene, view: dict, uv: np.ndarray) -> np.ndarray:
    """Surface points (N, 3) under image points (N, 2) of a view (nan where a ray misses)."""
    intr = intrinsics(view)
    R, t = np.asarray(view["R"]), np.asarray(view["t"])
    d = np.stack([(uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy,
                  np.ones(len(uv))], 1) @ R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c = camera_center(R, t)
    hit = scene.cast(np.broadcast_to(c, d.shape), d)["t_hit"].astype(float)
    hit[~np.isfinite(hit)] = np.nan
    return c + hit[:, None] * d


def densify(trace, step_px: float = 1.0) -> np.ndarray:
    """A polyline resampled every ``step_px``."""
    trace = np.asarray(trace, float)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(trace, axis=0), axis=1))]
    q = np.linspace(0.0, s[-1], int(np.ceil(s[-1] / step_px)) + 1)
    return np.stack([np.interp(q, s, trace[:, k]) for k in range(2)], 1)


def cast_dense(scene: RaycastScene, view: dict, dense: np.ndarray) -> np.ndarray:
    """A dense image polyline of a view cast onto the surface (N, 3); misses interpolated."""
    X = cast_trace(scene, view, dense)
    ok = np.isfinite(X).all(1)
    if ok.mean() < 0.95:
        raise SystemExit(f"a trace: {np.sum(~ok)} of {len(ok)} rays miss the scan")
    idx = np.arange(len(dense))
    return np.stack([np.interp(idx, idx[ok], X[ok, k]) for k in range(3)], 1)


def view_points(dense: np.ndarray, X: np.ndarray, start: np.ndarray, end: np.ndarray
                ) -> np.ndarray:
    """The view's 12 points on its trace: from the trace point nearest (3D) to the side's
    ``start`` to the one nearest to its ``end``, at equal lengths of the surface trace
    measured in the side plane (y, z)."""
    i = int(np.argmin(np.linalg.norm(X - start, axis=1)))
    j = int(np.argmin(np.linalg.norm(X - end, axis=1)))
    dense, X = dense[i:j + 1], X[i:j + 1]
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(X[:, 1:], axis=0), axis=1))]
    k = np.interp(np.linspace(0.0, arc[-1], COUNT), arc, np.arange(len(arc)))
    return np.stack([np.interp(k, np.arange(len(arc)), dense[:, c]) for c in range(2)], 1)


def triangulate(Ps: list[np.ndarray], uvs: np.ndarray) -> np.ndarray:
    """Linear DLT, then least squares on the reprojection error."""
    from scipy.optimize import least_squares

    A = np.concatenate([[u * P[2] - P[0], v * P[2] - P[1]] for P, (u, v) in zip(Ps, uvs)])
    X = np.linalg.svd(A)[2][-1]
    X = X[:3] / X[3]

    def residual(X):
        return np.concatenate([project(P, X)[0] - uv for P, uv in zip(Ps, uvs)])

    return least_squares(residual, X).x


def best_on_surface(vertices, faces, Ps, uvs, start: np.ndarray, radius_mm: float = 6.0,
                    steps: int = 24) -> np.ndarray:
    """The surface point within ``radius_mm`` of ``start`` with the least reprojection error
    (triangles sampled on a barycentric grid, then the best triangle refined)."""
    near = np.where(np.linalg.norm(vertices - start, axis=1) < radius_mm + 10)[0]
    tris = faces[np.isin(faces, near).any(1)]
    i, j = np.meshgrid(np.arange(steps + 1), np.arange(steps + 1))
    keep = i + j <= steps
    bary = np.stack([i[keep], j[keep], steps - i[keep] - j[keep]], 1) / steps
    best, best_cost = start, np.inf
    for _ in range(2):
        pts = np.einsum("kc,tcd->tkd", bary, vertices[tris]).reshape(-1, 3)
        pts = pts[np.linalg.norm(pts - start, axis=1) <= radius_mm]
        if not len(pts):
            break
        cost = sum(((project(P, pts) - uv) ** 2).sum(1) for P, uv in zip(Ps, uvs))
        k = int(np.argmin(cost))
        if cost[k] < best_cost:
            best, best_cost = pts[k], cost[k]
        # refine: the triangles around the best point, on a finer grid
        tris = faces[np.isin(faces, np.argsort(np.linalg.norm(vertices - best, axis=1))[:6]
                             ).any(1)]
        steps *= 3
        i, j = np.meshgrid(np.arange(steps + 1), np.arange(steps + 1))
        keep = i + j <= steps
        bary = np.stack([i[keep], j[keep], steps - i[keep] - j[keep]], 1) / steps
    return best


def build(doc: dict, subject) -> dict:
    import trimesh

    scene = RaycastScene()
    scene.add(subject.vertices, subject.faces)
    mesh = trimesh.Trimesh(subject.vertices, subject.faces, process=False)
    views = doc["views"]
    contour, per_point = {}, {}
    for side in SIDES:
        names = [n for n, v in views.items() if v["side"] == side and v.get("trace")]
        Ps = [projection(views[n]) for n in names]
        cast = []
        for n in names:
            dense = densify(views[n]["trace"])
            cast.append((dense, cast_dense(scene, views[n], dense)))
        # The ends: the mean of the views' surface points at the traces' ends, on the surface.
        ends = np.array([[X[0], X[-1]] for _, X in cast])  # (V, 2, 3)
        start, end = trimesh.proximity.closest_point(mesh, ends.mean(0))[0]
        end_spread = np.linalg.norm(ends - ends.mean(0), axis=2)  # (V, 2)
        uv = []
        for n, (dense, X) in zip(names, cast):
            pts = view_points(dense, X, start, end)
            views[n]["points_px"] = pts.round(2).tolist()
            uv.append(pts)
        uv = np.array(uv)  # (V, 12, 2)
        X = np.array([triangulate(Ps, uv[:, k]) for k in range(COUNT)])
        closest, snap, _ = trimesh.proximity.closest_point(mesh, X)
        final = np.array([best_on_surface(subject.vertices, subject.faces, Ps, uv[:, k],
                                          closest[k]) for k in range(COUNT)])
        single = np.array([cast_trace(scene, views[n], uv[v]) for v, n in enumerate(names)])
        spread = np.sqrt(np.nanmean(((single - final) ** 2).sum(2), axis=0))
        err_dlt = np.array([np.linalg.norm(project(P, X) - uv[v], axis=1)
                            for v, P in enumerate(Ps)])
        err_snap = np.array([np.linalg.norm(project(P, closest) - uv[v], axis=1)
                             for v, P in enumerate(Ps)])
        err = np.array([np.linalg.norm(project(P, final) - uv[v], axis=1)
                        for v, P in enumerate(Ps)])
        for v, n in enumerate(names):
            views[n]["reprojection_px"] = err[v].round(2).tolist()
            views[n]["reprojection_rms_px"] = round(float(np.sqrt((err[v] ** 2).mean())), 2)
            views[n]["reprojection_rms_px_triangulated"] = round(
                float(np.sqrt((err_dlt[v] ** 2).mean())), 2)
        contour[side] = final.round(3).tolist()
        per_point[side] = {
            "views": names,
            "triangulated_mm": X.round(3).tolist(),
            "reprojection_rms_px_triangulated": np.sqrt((err_dlt ** 2).mean(0)).round(2).tolist(),
            "snap_mm": snap.round(2).tolist(),
            "reprojection_rms_px_snapped": np.sqrt((err_snap ** 2).mean(0)).round(2).tolist(),
            "moved_on_surface_mm": np.linalg.norm(final - closest, axis=1).round(2).tolist(),
            "reprojection_rms_px": np.sqrt((err ** 2).mean(0)).round(2).tolist(),
            "single_view_spread_mm": spread.round(2).tolist(),
            "trace_end_spread_mm": {"start": end_spread[:, 0].round(2).tolist(),
                                    "end": end_spread[:, 1].round(2).tolist()},
            "px_per_mm": round(float(np.median([
                np.linalg.norm(project(P, final[:1]) - project(P, final[:1] + [0, 1, 0]))
                for P in Ps])), 2),
        }
    doc["contour"] = contour
    doc["per_point"] = per_point
    doc["summary"] = {
        side: {"reprojection_rms_px_per_view": {
                   n: views[n]["reprojection_rms_px"] for n in pp["views"]},
               "reprojection_rms_px_all": round(float(np.sqrt(np.mean(
                   [np.square(views[n]["reprojection_px"]) for n in pp["views"]]))), 2),
               "snap_mm_median": round(float(np.median(pp["snap_mm"])), 2),
               "snap_mm_max": round(float(np.max(pp["snap_mm"])), 2),
               "single_view_spread_mm_median": round(float(np.median(
                   pp["single_view_spread_mm"])), 2),
               "single_view_spread_mm_max": round(float(np.max(pp["single_view_spread_mm"])), 2),
               "px_per_mm_in_labelling_views": pp["px_per_mm"]}
        for side, pp in per_point.items()}
    return doc


def overlay(img: np.ndarray, view: dict, contour: np.ndarray | None, zoom: int = 2,
            margin: int = 40) -> np.ndarray:
    """Enlarged crop around the ear: trace red, the view's 12 points green, the stored
    contour reprojected magenta (numbered)."""
    bgr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    layers = [np.asarray(view.get(k), float) for k in ("trace", "points_px") if view.get(k)]
    proj = project(projection(view), contour) if contour is not None else None
    pts = np.concatenate(layers + ([proj] if proj is not None else []))
    lo = np.maximum(pts.min(0) - margin, 0).astype(int)
    hi = np.minimum(pts.max(0) + margin, [img.shape[1], img.shape[0]]).astype(int)
    crop = cv2.resize(bgr[lo[1]:hi[1], lo[0]:hi[0]], None, fx=zoom, fy=zoom,
                      interpolation=cv2.INTER_CUBIC)

    def up(p):
        return tuple(np.round((np.asarray(p) - lo + 0.5) * zoom - 0.5).astype(int))

    if view.get("trace"):
        cv2.polylines(crop, [np.array([up(p) for p in view["trace"]])], False, (0, 0, 255), 1,
                      cv2.LINE_AA)
    for key, colour in (("points_px", (0, 255, 0)), ("contour", (255, 0, 255))):
        pts = view.get(key) if key == "points_px" else proj
        if pts is None or not len(pts):
            continue
        for i, p in enumerate(pts):
            q = up(p)
            cv2.circle(crop, q, 4, colour, 1, cv2.LINE_AA)
            cv2.putText(crop, str(i + 1), (q[0] + 5, q[1] - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                        colour, 1, cv2.LINE_AA)
    return crop


def check_views(contour: dict) -> dict:
    """Views not used for labelling: yaw 70 deg, elevation -5 deg, roll 8 deg, 350 mm from the
    ear's centre, and one bench-like small view (yaw 55 deg, elevation 18 deg, ear ~120 px)."""
    views = {}
    for side in SIDES:
        c = np.asarray(contour[side])
        centre = c.mean(0)
        s = 1.0 if side == "left" else -1.0
        for name, yaw, elev, roll, dist, size, ear_px in (
                ("check_a", 70, -5, 8, 350, 720, 260), ("check_b", 55, 18, -6, 450, 480, 120)):
            y, e = np.radians(yaw), np.radians(elev)
            eye = centre + dist * np.array([s * np.sin(y) * np.cos(e), np.sin(e),
                                            np.cos(y) * np.cos(e)])
            R, _ = look_at(eye, centre, [0.0, 1.0, 0.0])
            a = np.radians(roll)
            Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
            R = Rz @ R
            f = ear_px * dist / np.ptp(c[:, 1])
            views[f"{side}_{name}"] = {
                "side": side, "yaw_deg": yaw, "elevation_deg": elev, "roll_deg": roll,
                "distance_mm": dist, "width": size, "height": size, "fx": f, "fy": f,
                "cx": (size - 1) / 2, "cy": (size - 1) / 2, "R": R.tolist(),
                "t": (-R @ eye).tolist()}
    return views


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("command", choices=("render", "build", "check"))
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--traces", type=Path, help="JSON {view: {'trace': [[u, v], ...]}}")
    parser.add_argument("--out", type=Path, default=ROOT / "out/james_ear_contour")
    parser.add_argument("--overlay", action="store_true")
    args = parser.parse_args(argv)
    doc = json.loads(args.data.read_text())
    subject = make_subject(SynthConfig(subject="james"))
    if args.command == "build":
        if args.traces:
            for name, lab in json.loads(args.traces.read_text()).items():
                doc["views"][name]["trace"] = lab["trace"]
        doc = build(doc, subject)
        args.data.write_text(json.dumps(doc, indent=1) + "\n")
        for side, pp in doc["per_point"].items():
            print(f"{side}: reprojection rms (px) per point {pp['reprojection_rms_px']}; snap "
                  f"(mm) {pp['snap_mm']}; single-view spread (mm) {pp['single_view_spread_mm']}")
        for name, v in doc["views"].items():
            print(f"{name}: reprojection rms {v['reprojection_rms_px']} px "
                  f"(triangulated, off the surface: {v['reprojection_rms_px_triangulated']} px)")
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    room = Room.random(np.random.default_rng(doc["room_seed"]))
    views = dict(doc["views"]) if args.command == "render" else {}
    if args.command == "check" or args.overlay:
        views.update(check_views(doc["contour"]))
    for name, view in views.items():
        img = render_view(subject, room, view)
        cv2.imwrite(str(args.out / f"{name}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        if args.command == "check" or args.overlay:
            contour = np.asarray(doc["contour"][view["side"]]) if "contour" in doc else None
            cv2.imwrite(str(args.out / f"{name}_overlay.png"), overlay(img, view, contour))
        print(args.out / f"{name}.png", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
