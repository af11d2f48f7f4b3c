"""The figures of a capture run's ``report.json`` in words, rounded, with their units, and the
warnings a user must read before trusting the mesh: what the capture page and the Prefect
UI's summary show."""

from __future__ import annotations

import math

from facecap_core.coarse import ears_summary, scale_summary
from facecap_core.measure import summary as measurements_summary

COVERAGE_WARN_DEG = 120.0
"""Views spanning less yaw than this round the head get a warning: a full sweep spans about
180°, and under this the sides of the head and the ears are seen by few views or none."""


def _count(n: int, what: str) -> str:
    return f"{n} {what}{'' if n == 1 else 's'}"


def _sanity_counts(sanity: dict) -> str:
    """``314 self-intersecting triangle pairs, 2 flipped triangles`` (what is wrong only)."""
    parts = [_count(sanity.get(key) or 0, what) for key, what in (
        ("self_intersecting_pairs", "self-intersecting triangle pair"),
        ("flipped", "flipped triangle"), ("stretched_edges", "stretched edge"))
        if sanity.get(key)]
    return ", ".join(parts) or "no count given"


def _scores(sc: dict) -> str:
    a, c = sc["accuracy"], sc["completion"]
    return (f"mean {a['mean']:.3f} mm, median {a['median']:.3f} mm; completion mean "
            f"{c['mean']:.3f} mm, median {c['median']:.3f} mm")


def figure_rows(report: dict) -> list[tuple[str, str, str]]:
    """(key, label, text) of the figures that matter, in words, rounded, with their units:
    what the page and the Prefect UI's summary show."""
    fig, rows = report.get("figures", {}), []
    scale = fig.get("scale") or {}
    parts = []
    if fig.get("metric_scale") is not None:
        parts.append(f"{fig['metric_scale']:.4g} mm per camera unit")
    if scale.get("sigma_pct") is not None:
        parts.append(scale_summary(scale))
    if parts:
        rows.append(("metric_scale", "Metric scale", ", ".join(parts)))
    if fig.get("keyframes") is not None:
        dropped = fig.get("dropped_keyframes") or []
        rows.append(("keyframes", "Keyframes", str(fig["keyframes"]) if not dropped else
                     f"{fig['keyframes']} registered, {len(dropped)} left out (frames "
                     f"{', '.join(str(d.get('frame_index')) for d in dropped)})"))
    if fig.get("focal_px") is not None:
        rows.append(("focal_px", "Focal length", f"{fig['focal_px']:.1f} px"))
    solve = solve_summary(fig.get("solve"))
    if solve:
        rows.append(("solve", "Camera solve", solve))
    coverage = fig.get("coverage") or {}
    if coverage.get("yaw_span_deg") is not None:
        rows.append(("coverage", "Coverage", f"yaw {coverage['yaw_min_deg']:+.0f}° to "
                     f"{coverage['yaw_max_deg']:+.0f}° round the head "
                     f"({coverage['yaw_span_deg']:.0f}°; a full sweep spans about 180°)"))
    if fig.get("ears"):
        rows.append(("ears", "Ears", ears_summary(fig["ears"])))
    elif fig.get("metric_scale") is not None:  # the coarse stage ran, and said nothing
        rows.append(("ears", "Ears", "nothing is known about the ears: this run's report "
                     "has no ear checks"))
    sanity = fig.get("mesh_sanity") or {}
    if "ok" in sanity:
        rows.append(("mesh_sanity", "Mesh check", "passed: no flipped triangle, stretched "
                     "edge or self-intersection" if sanity["ok"] else
                     f"failed: {_sanity_counts(sanity)}"))
    noise = fig.get("cloud_noise") or {}
    if noise.get("noise_mm") is not None:
        expected = (f"; the fit expects {noise['reference_mm']:g} mm"
                    if noise.get("reference_mm") is not None else "")
        rows.append(("cloud_noise", "Cloud noise", f"{noise['noise_mm']:.3f} mm (the fused "
                     f"points' median standard error over the face{expected})"))
    rough = fig.get("roughness") or {}
    if rough.get("bent_share_pct") is not None:
        rows.append(("roughness", "Surface", f"{rough['bent_share_pct']:.1f} % of the face's "
                     f"edges bent over {rough['bent_deg']:g}°, median bend "
                     f"{rough['median_bend_deg']:.1f}° (smooth skin: under 7 % and 3°)"))
    if fig.get("parts"):
        rows.append(("parts", "Support by part", parts_summary(fig["parts"])))
    if isinstance(fig.get("measurements"), dict) and measurements_summary(fig["measurements"]):
        anatomical = any(isinstance(m, dict) and isinstance(m.get("anatomical"), dict)
                         for m in fig["measurements"].values())
        rows.append(("measurements", "Measurements", measurements_summary(fig["measurements"])
                     + (" (anatomical: ± the metric scale's and the landmarks' placement 1σ)"
                        if anatomical else " (straight; ± the metric scale's 1σ)")))
    for protocol, sc in (fig.get("evaluation") or {}).items():
        rows.append((f"evaluation_{protocol}", f"Accuracy ({protocol})", _scores(sc)))
        ears = sc.get("ears") or {}
        if (ears.get("accuracy") or {}).get("median") is not None and \
                (ears.get("completion") or {}).get("median") is not None:
            rows.append((f"ears_{protocol}", f"Ears accuracy ({protocol})", _scores(ears)))
    return rows


def parts_summary(parts: dict) -> str:
    """Each part of the face in words (``report.json`` ``figures.parts``, see
    :mod:`facecap_core.fitting.quality`): the mesh's distance from its own cloud, the cloud
    under it and its noise, its landmarks' distance from the cloud; the parts the cloud does
    not support last."""
    said, unsupported = [], []
    for name, p in parts.items():
        if not isinstance(p, dict):
            continue
        if not p.get("supported"):
            unsupported.append(f"{name} ({_pct(p.get('supported_share'))} under cloud)")
            continue
        words = [f"mesh {_mm(p.get('mesh_to_cloud_mm'), signed=True)} from its cloud "
                 f"(typically {_mm(p.get('mesh_to_cloud_abs_mm'))})",
                 f"{_pct(p.get('supported_share'))} under cloud",
                 f"cloud noise {_mm(p.get('cloud_noise_mm'))}"]
        if p.get("landmark_to_cloud_mm") is not None:
            words.append(f"landmarks {_mm(p['landmark_to_cloud_mm'])} off the cloud")
        said.append(f"{name}: " + ", ".join(words))
    if unsupported:
        said.append("shaped by the template, not the capture (too little cloud): "
                    + ", ".join(unsupported))
    return "; ".join(said)


def solve_summary(solve) -> str:
    """The camera solve's own figures (the pose stage's ``solve``) in words: what a user
    checks a solve by (a phone's field of view, the principal point near the image's
    centre, a reprojection error under a pixel, tracks over several views, the views' turn
    agreeing with the tracker's); "" without any."""
    if not isinstance(solve, dict):
        return ""
    number = {key: finite_number(solve.get(key)) for key in (
        "turn_deg", "tracked_turn_deg", "track_length", "largest_step_ratio")}
    fov, centre = _pair(solve.get("field_of_view_deg")), _pair(solve.get("principal_point_px"))
    error = solve.get("reprojection_px") if isinstance(solve.get("reprojection_px"), dict) else {}
    parts = []
    if fov:
        parts.append(f"field of view {fov[0]:.0f}° × {fov[1]:.0f}°")
    if centre:
        held = (" (held at the image centre: the tracks put it further than a phone's)"
                if solve.get("principal_point_held") is True else "")
        parts.append(f"principal point ({centre[0]:.1f}, {centre[1]:.1f}) px{held}")
    if finite_number(error.get("median")) is not None:
        parts.append(f"reprojection {error['median']:.2f} px median")
    if number["track_length"] is not None:
        parts.append(f"points seen by {number['track_length']:.1f} views on average")
    if number["turn_deg"] is not None:
        tracked = (f" (the tracker's {number['tracked_turn_deg']:.0f}°)"
                   if number["tracked_turn_deg"] is not None else "")
        parts.append(f"views turn {number['turn_deg']:.0f}° along the sweep{tracked}")
    return "; ".join(parts)


def _pair(value) -> tuple[float, float] | None:
    """``value`` if it is a list of two finite numbers, else None."""
    if not isinstance(value, list) or len(value) != 2:
        return None
    pair = tuple(finite_number(v) for v in value)
    return None if None in pair else pair


def finite_number(value) -> float | None:
    """``value`` if it is a finite number (not a boolean), else None: what a figure read from
    a report (anyone's to write) may be shown as."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        value = float(value)
    except OverflowError:  # an integer past the floats
        return None
    return value if math.isfinite(value) else None


def _mm(value, signed: bool = False) -> str:
    value = finite_number(value)
    if value is None:
        return "–"
    return f"{value:+.2f} mm" if signed else f"{value:.2f} mm"


def _pct(share) -> str:
    share = finite_number(share)
    return "–" if share is None else f"{100 * share:.0f} %"


def warnings(report: dict) -> list[tuple[str, str]]:
    """(key, text) of what in ``report`` a user must know before trusting the mesh, the worst
    first: a mesh that fails its checks, keyframes left out, a narrow sweep, a noisy cloud."""
    fig, found = report.get("figures", {}), []
    sanity = fig.get("mesh_sanity") or {}
    if sanity.get("ok") is False:
        found.append(("mesh_sanity", f"The mesh fails its checks: {_sanity_counts(sanity)} "
                      "after the fit relaxed what it could; the surface is wrong there."))
    dropped = fig.get("dropped_keyframes") or []
    if dropped:
        reasons = sorted({str(d.get("reason", "no reason given")) for d in dropped})
        total = (fig.get("keyframes") or 0) + len(dropped)
        found.append(("dropped_keyframes", f"{len(dropped)} of {total} keyframes were left "
                      f"out ({'; '.join(reasons)}): frames "
                      f"{', '.join(str(d.get('frame_index')) for d in dropped)}."))
    span = (fig.get("coverage") or {}).get("yaw_span_deg")
    if span is not None and span < COVERAGE_WARN_DEG:
        found.append(("coverage", f"The views span only {span:.0f}° of yaw round the head "
                      "(a full sweep about 180°): the sides of the head and the ears are "
                      "seen by few views or none."))
    noise = fig.get("cloud_noise") or {}
    if noise.get("noise_mm") is not None and noise.get("reference_mm") is not None and \
            noise["noise_mm"] > noise["reference_mm"]:
        found.append(("cloud_noise", f"The fused cloud is noisy: {noise['noise_mm']:.3f} mm "
                      f"against the {noise['reference_mm']:g} mm the fit expects; the fit "
                      "trusted it less and smoothed the face more."))
    return found


def run_summary(report: dict) -> str:
    """``3 artifacts computed, 1 reused, 81.5 s``."""
    computed = report.get("computed", 0)
    return (f"{computed} artifact{'' if computed == 1 else 's'} computed, "
            f"{report.get('cached', 0)} reused, {report.get('wall_seconds', 0):.1f} s")
