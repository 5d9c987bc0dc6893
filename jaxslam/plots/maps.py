"""The map of one run: true trunks, the estimated landmarks with their 2-sigma ellipses
(enlarged by one stated factor, with a true-scale zoom), and the true, estimated and smoothed
paths.
"""
from __future__ import annotations

import os
import tomllib
import warnings

import numpy as np

from jaxslam.plots import figure, labels
from jaxslam.plots.inputs import ExampleRun, load_example_run
from jaxslam.plots.labels import StudyInfo, map_title, tree_seen_labels

SIGMA_SCALE = 2.0  # ellipses are drawn at 2 standard deviations along each principal axis
# Scaled ellipses: the median full major axis is drawn at about this fraction of the map.
ELLIPSE_TARGET_FRACTION = 0.015
_INSET_GID = "true_scale_inset"
_ELLIPSES_GID = "landmark_ellipses"


def covariance_ellipses(cov, scale: float = SIGMA_SCALE):
    """Axis lengths and orientation of ``scale``-sigma ellipses of 2x2 covariances.

    cov: (M, 2, 2) symmetric. Returns (width (M,), height (M,), angle_deg (M,)): full axis
    lengths ``2 * scale * sqrt(eigenvalue)`` (major first) and the major axis angle from +x.
    """
    cov = np.asarray(cov, np.float64)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    eigenvalues, eigenvectors = np.linalg.eigh(cov)  # ascending
    eigenvalues = np.clip(eigenvalues, 0.0, None)
    major = eigenvectors[..., :, 1]
    angle = np.degrees(np.arctan2(major[..., 1], major[..., 0]))
    return (2.0 * scale * np.sqrt(eigenvalues[..., 1]),
            2.0 * scale * np.sqrt(eigenvalues[..., 0]), angle)


def ellipse_scale(widths, extent: float, target: float = ELLIPSE_TARGET_FRACTION) -> float:
    """Magnification of the landmark ellipses on a map of size ``extent`` [m].

    widths: (M,) full major axes [m]. Returns the largest of 1, 2, 5, 10, 20, 50, ... that
    keeps the median width times the factor at or below ``target * extent``; 1 when the
    ellipses are already that large (or there are none), so they are never shrunk.
    """
    widths = np.asarray(widths, np.float64)
    widths = widths[np.isfinite(widths) & (widths > 0)]
    if widths.size == 0 or not extent > 0:
        return 1.0
    wanted = target * extent / float(np.median(widths))
    if wanted < 2.0:
        return 1.0
    decade = 10.0 ** np.floor(np.log10(wanted))
    return float(decade * max(m for m in (1.0, 2.0, 5.0) if m * decade <= wanted))


def _map_extent(run: ExampleRun) -> float:
    """Side [m] of the bounding square of everything a map draws."""
    points = np.concatenate([run.truth_pose[:, :2], run.mean_pose[:, :2], run.tree_centres,
                             run.landmark_mean[run.active]])
    return float(np.max(np.ptp(points, axis=0))) if len(points) else 0.0


def _draw_map_layers(ax, run: ExampleRun, scale: float, seen_texts, legend: bool) -> list:
    """Trunks, landmarks with ``scale`` x 2-sigma ellipses and the paths on ``ax``.

    Returns the legend entries [(handle, text)] in reading order (empty if not ``legend``).
    """
    from matplotlib.collections import EllipseCollection, PatchCollection
    from matplotlib.patches import Circle, Ellipse

    entries = []
    seen = run.tree_seen if run.tree_seen is not None else np.ones(len(run.tree_radii), bool)
    groups = ((seen, "saddlebrown", seen_texts[0]), (~seen, "darkgray", seen_texts[1]))
    if run.tree_seen is None:
        groups = ((seen, "saddlebrown", "true trunks: {n}"),)
    for mask, colour, text in groups:
        if not mask.any():
            continue
        centres, radii = run.tree_centres[mask], run.tree_radii[mask]
        ax.add_collection(PatchCollection([Circle(tuple(c), r) for c, r in zip(centres, radii)],
                                          facecolor=colour, edgecolor="none", alpha=0.6))
        handle = ax.scatter(centres[:, 0], centres[:, 1], s=14, marker="o", facecolor="none",
                            edgecolor=colour, linewidth=1.0)
        entries.append((handle, text.format(n=int(mask.sum()))))
    mean, cov = run.landmark_mean[run.active], run.landmark_cov[run.active]
    if len(mean):
        width, height, angle = covariance_ellipses(cov)
        ellipses = EllipseCollection(scale * width, scale * height, angle, units="xy",
                                     offsets=mean, offset_transform=ax.transData,
                                     facecolor="none", edgecolor="tab:blue", linewidth=1.0)
        ellipses.set_gid(_ELLIPSES_GID)
        ax.add_collection(ellipses)
        handle = ax.scatter(mean[:, 0], mean[:, 1], s=18, marker="+", color="tab:blue")
        entries.append((handle, f"estimated landmarks: {len(mean)}"))
        proxy = Ellipse((0, 0), 1.0, 0.6, facecolor="none", edgecolor="tab:blue")
        entries.append((proxy, f"landmark {SIGMA_SCALE:g}σ ellipse" + (
            f" ×{scale:g} (enlarged to be visible)" if scale != 1 else " (true scale)")))
    if len(run.truth_pose):
        line, = ax.plot(run.truth_pose[:, 0], run.truth_pose[:, 1], color="black",
                        linewidth=1.8)
        entries.append((line, "true path"))
    line, = ax.plot(run.mean_pose[:, 0], run.mean_pose[:, 1], color="tab:red", linewidth=1.4,
                    linestyle="--")
    entries.append((line, "estimated path (weighted mean)"))
    if run.smoothed_pose is not None:
        line, = ax.plot(run.smoothed_pose[:, 0], run.smoothed_pose[:, 1], color="tab:green",
                        linewidth=1.4, linestyle="-.")
        entries.append((line, "smoothed path"))
    start = run.truth_pose[0, :2] if len(run.truth_pose) else (
        run.mean_pose[0, :2] if len(run.mean_pose) else None)
    if start is not None:
        line, = ax.plot(*start, marker="s", color="black", markersize=7, linestyle="none")
        entries.append((line, "start"))
    for handle, text in entries:
        handle.set_label(text)  # so the artists can be found by their legend text
    return entries if legend else []


def _inset_window(run: ExampleRun, index: int, half_major: float) -> float:
    """Half-side [m] of the inset around active landmark ``index``: its 2-sigma ellipse and
    its nearest true trunk (when that is within 1 m) fit with a margin."""
    centre = run.landmark_mean[index]
    reach = half_major
    if len(run.tree_centres):
        gaps = np.hypot(*(run.tree_centres - centre).T)
        nearest = int(np.argmin(gaps))
        reach = max(reach, min(gaps[nearest] + run.tree_radii[nearest], 1.0))
    return 1.5 * max(reach, 0.1)


def _add_true_scale_inset(ax, run: ExampleRun, seen_texts) -> None:
    """A zoom at true scale (unscaled 2-sigma ellipses) on the least certain active landmark
    (largest major axis), beside the map, its region outlined on the map."""
    active = np.flatnonzero(run.active)
    width, _, _ = covariance_ellipses(run.landmark_cov[active])
    pick = int(np.argmax(width))
    index = active[pick]
    half = _inset_window(run, index, 0.5 * width[pick])
    inset = ax.inset_axes([1.04, 0.0, 0.5, 0.5])
    inset.set_gid(_INSET_GID)
    _draw_map_layers(inset, run, 1.0, seen_texts, legend=False)
    cx, cy = run.landmark_mean[index]
    inset.set_xlim(cx - half, cx + half)
    inset.set_ylim(cy - half, cy + half)
    inset.set_aspect("equal", adjustable="box")
    inset.set_title(f"zoom at true scale ({SIGMA_SCALE:g}σ ellipse ×1):\n"
                    "the least certain landmark (outlined on the map)", fontsize=8)
    inset.set_xlabel("x [m]", fontsize=8)
    inset.set_ylabel("y [m]", fontsize=8)
    inset.tick_params(labelsize=7)
    inset.grid(True, alpha=0.3)
    ax.indicate_inset_zoom(inset, edgecolor="0.3")


def map_figure(example, title: str | None = None, *, info: StudyInfo | None = None,
               scale: float | None = None, inset: bool | None = None):
    """The map of one run as a Figure (not saved; ``plot_map`` saves it).

    Draws the true trunks (circles of their radius, with a marker so thin trunks show; grey
    when the optional ``tree_seen`` mask says the run never saw them, ``tree_seen_labels``),
    the active landmarks of the highest-weight particle with their 2-sigma ellipses, the true,
    estimated and (when given) smoothed paths, and the start.

    Uncertainty: landmark standard deviations are centimetres on a map of tens of metres, so
    true-scale ellipses vanish under their markers. Two views are drawn: on the map every
    ellipse is enlarged by one stated factor (``ellipse_scale``: 1, 2, 5, 10, ... chosen so
    the median ellipse is about 1.5 % of the map; the legend says e.g. "landmark 2σ ellipse
    ×10"), which shows where the map is uncertain and in which direction; beside it a zoom
    at true scale on the least certain landmark shows the real size against its trunk and
    the true centre, which an enlarged ellipse would misstate. The zoom is drawn only when
    the map's factor is above 1.

    Args:
      example: path to ``example_run.npz`` or a mapping of its arrays (see ``ExampleRun``).
      title: the title (default: ``map_title(info)`` for a study, else a generic one).
      info: the study (``study_info``) for the title and the ``tree_seen`` legend texts.
      scale: ellipse magnification (default: ``ellipse_scale``).
      inset: draw the true-scale zoom (default: when the magnification is above 1).
    Returns:
      matplotlib.figure.Figure; its first axes is the map.
    """
    run = load_example_run(example)
    seen_texts = tree_seen_labels(info)
    active_cov = run.landmark_cov[run.active]
    if scale is None:
        scale = ellipse_scale(covariance_ellipses(active_cov)[0], _map_extent(run))
    fig = figure.new_figure((8, 8))
    ax = fig.add_subplot()
    entries = _draw_map_layers(ax, run, scale, seen_texts, legend=True)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if title is None:
        title = map_title(info) if info is not None else \
            "Map: true trunks and estimated landmarks"
    ax.set_title(title, fontsize=11)
    ax.grid(True, alpha=0.3)
    ax.legend([h for h, _ in entries], [t for _, t in entries], loc="upper left",
              bbox_to_anchor=(1.01, 1.0), fontsize=9, framealpha=0.9)
    if (scale > 1 if inset is None else inset) and run.active.any():
        _add_true_scale_inset(ax, run, seen_texts)
    return fig


def plot_map(example, out_png, title: str | None = None, *, info: StudyInfo | None = None,
             **options) -> str:
    """Build ``map_figure`` and save it as a PNG; returns the path.

    When ``example`` is a path and neither ``title`` nor ``info`` is given, the study of the
    folder holding the file (its ``study.toml``, if any) names the title.
    """
    if info is None and title is None and isinstance(example, (str, os.PathLike)):
        try:
            info = labels.study_info(os.path.dirname(os.path.abspath(os.fspath(example))))
        except (ValueError, TypeError, tomllib.TOMLDecodeError) as error:
            warnings.warn(f"map title: the study.toml next to {os.fspath(example)} is not "
                          f"readable ({error}); using a generic title")
    return figure.save_figure(map_figure(example, title, info=info, **options), out_png)
