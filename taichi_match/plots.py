"""Pictures of maps, matches and surfaces (matplotlib, an optional dependency: ``[plots]``)."""

import os

import numpy as np

from ._errors import InvalidOptionError
from ._grid import GridMap

__all__ = ["map_rgba", "draw_map", "draw_overlay", "check_picture_path", "save_overlay", "save_surface", "save_maps",
           "save_merge", "save_trajectories"]

UNKNOWN_RGB = (0.72, 0.82, 0.97)       # the paper draws unknown cells in blue


def _figure(**kwargs):
    """A ``matplotlib.figure.Figure`` made without pyplot: no backend chosen, no global figure
    registry, nothing to close; ``Figure.savefig`` picks the writer by the file's extension."""
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:       # pragma: no cover - depends on the environment
        raise ImportError("pictures need matplotlib: pip install 'taichi-match[plots]'") from exc
    return Figure(**kwargs)


def map_rgba(grid: GridMap, *, tint=None, alpha_free=1.0, alpha_occupied=1.0, stretch=False):
    """RGBA image of a map: free white, occupied black (or ``tint``), unknown blue (or clear).

    ``stretch`` maps the largest probability to black, to make a faint blur visible.
    """
    p = grid.prob
    known = ~np.isnan(p)
    q = np.nan_to_num(p, nan=0.0)
    if stretch and q.max() > 0:
        q = q / q.max()
    rgba = np.zeros(p.shape + (4,))
    if tint is None:
        grey = 1.0 - q
        rgba[..., 0] = rgba[..., 1] = rgba[..., 2] = grey
        rgba[..., 3] = 1.0
        rgba[~known, :3] = UNKNOWN_RGB
    else:
        rgba[..., :3] = tint
        rgba[..., 3] = np.where(known, alpha_free + (alpha_occupied - alpha_free) * q, 0.0)
    return rgba


def draw_map(ax, grid: GridMap, pose=(0.0, 0.0, 0.0), **style):
    """Draw ``grid`` on ``ax`` in frame A, placed by ``pose`` (r_A2B of the grid's frame)."""
    from matplotlib.transforms import Affine2D

    rows, cols = grid.shape
    gx, gy, yaw = grid.corner_pose
    transform = (Affine2D().rotate(yaw).translate(gx, gy).rotate(pose[2]).translate(pose[0], pose[1])
                 + ax.transData)
    return ax.imshow(map_rgba(grid, **style), origin="lower", transform=transform, interpolation="nearest",
                     extent=(0.0, cols * grid.resolution, 0.0, rows * grid.resolution))


def draw_overlay(ax, a: GridMap, b: GridMap, pose, *, covariance=None, title=None):
    """A with B placed at ``pose`` (red, translucent), and the 95 % ellipse of ``covariance``."""
    draw_map(ax, a)
    draw_map(ax, b, pose, tint=(0.85, 0.1, 0.1), alpha_free=0.12, alpha_occupied=0.9)
    x0, x1, y0, y1 = a.extent
    pad = 0.1 * max(x1 - x0, y1 - y0)
    if covariance is not None:
        from matplotlib.patches import Ellipse

        evals, evecs = np.linalg.eigh(np.asarray(covariance)[:2, :2])
        from scipy import stats
        k = stats.chi2.ppf(0.95, 2)
        w, h = 2.0 * np.sqrt(k * np.maximum(evals, 0.0))
        angle = np.degrees(np.arctan2(evecs[1, 0], evecs[0, 0]))
        ax.add_patch(Ellipse((pose[0], pose[1]), w, h, angle=angle, fill=False, color="c", lw=2,
                             label="95 % (x, y) covariance"))
    ax.plot(pose[0], pose[1], "r+", ms=10)
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if title:
        ax.set_title(title, fontsize=10)


def check_picture_path(path):
    """Raise InvalidOptionError unless ``path`` names a .png, .pdf or .svg file (its format) in an
    existing folder."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext not in (".png", ".pdf", ".svg") or os.path.isdir(path):
        raise InvalidOptionError(f"the picture must be a .png, .pdf or .svg file; got {os.fspath(path)!r}")
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    if not os.path.isdir(folder):
        raise InvalidOptionError(f"no folder {folder!r} for the picture {os.fspath(path)!r}")


def save_overlay(path, a: GridMap, b: GridMap, initial_pose, result, *, title=""):
    """Two panels, as the paper's Figs. 6-9: the initial setting and the final solution, saved to
    ``path``, whose extension (.png, .pdf, .svg) says the format."""
    check_picture_path(path)
    fig = _figure(figsize=(11, 5.2))
    axes = fig.subplots(1, 2)
    x, y, t = initial_pose
    draw_overlay(axes[0], a, b, initial_pose, title=f"initial  x={x:.2f} y={y:.2f} theta={t:.3f}")
    x, y, t = result.pose
    draw_overlay(axes[1], a, b, result.pose, covariance=result.covariance,
                 title=f"final  x={x:.3f} y={y:.3f} theta={t:.4f}  ({result.status.name})")
    axes[1].legend(loc="lower right", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def save_surface(path, xs, ys, z, *, title="", zlabel="e"):
    """A 3-D surface as the paper's Figs. 2, 4 and 5."""
    fig = _figure(figsize=(7.5, 5.5))
    ax = fig.add_subplot(projection="3d")
    gx, gy = np.meshgrid(xs, ys)
    ax.plot_surface(gx, gy, z, cmap="viridis", linewidth=0, antialiased=True, rcount=len(ys), ccount=len(xs))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel(zlabel)
    ax.view_init(elev=28, azim=-60)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def save_maps(path, raw: GridMap, blurred: GridMap, *, title=""):
    """The paper's Fig. 3: a map and its blurred version side by side."""
    fig = _figure(figsize=(10, 5))
    axes = fig.subplots(1, 2)
    peak = np.nanmax(blurred.prob) if np.any(~np.isnan(blurred.prob)) else 1.0
    for ax, grid, label, stretch in ((axes[0], raw, "original", False),
                                     (axes[1], blurred, f"blurred (grey stretched: black = {peak:.2f})", True)):
        draw_map(ax, grid, stretch=stretch)
        x0, x1, y0, y1 = grid.extent
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal")
        ax.set_title(label)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def save_merge(path, a: GridMap, b: GridMap, merged: GridMap, *, title=""):
    """Three panels: A, B (each in its own frame) and ``merged`` (``merge.merge_maps``, frame A),
    saved to ``path`` (.png, .pdf or .svg)."""
    check_picture_path(path)
    fig = _figure(figsize=(15, 5.2))
    axes = fig.subplots(1, 3)
    for ax, grid, label in ((axes[0], a, "A"), (axes[1], b, "B"), (axes[2], merged, "B merged into A")):
        draw_map(ax, grid)
        x0, x1, y0, y1 = grid.extent
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_title(label)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def save_trajectories(path, grid: GridMap, trajectories, *, title=""):
    """``grid`` with trajectories over it: ``trajectories`` maps a label to (poses (N, 3), colour,
    line style), all in the map's frame. The extension of ``path`` says the format."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext not in (".png", ".pdf", ".svg") or os.path.isdir(path):
        raise InvalidOptionError(f"the picture must be a .png, .pdf or .svg file; got {os.fspath(path)!r}")
    fig = _figure(figsize=(8, 8))
    ax = fig.subplots()
    x0, y0 = grid.origin
    h, w = grid.shape
    ax.imshow(np.nan_to_num(1.0 - grid.prob, nan=0.8), cmap="gray", vmin=0, vmax=1, origin="lower",
              extent=(x0, x0 + w * grid.resolution, y0, y0 + h * grid.resolution))
    for label, (poses, colour, style) in trajectories.items():
        poses = np.asarray(poses)
        ax.plot(poses[:, 0], poses[:, 1], color=colour, ls=style, lw=1.0, label=label)
    ax.set_title(title)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    fig.savefig(path, dpi=90, bbox_inches="tight")
