"""Map files: ROS ``map_server`` YAML + image, ``nav_msgs/OccupancyGrid``-style arrays, .npz.

Apart from the core (which never imports it). YAML through PyYAML, images through Pillow (the
``maps`` extra); what is ours is map_server's rules and the bounds on hostile files. ROS
conventions, as ``map_server`` loads a map:

- The YAML holds ``image`` (a path relative to the YAML), ``resolution``, ``origin: [x, y, yaw]``
  (the pose of the lower-left pixel in the map frame), ``negate``, ``occupied_thresh``,
  ``free_thresh`` and ``mode`` (``trinary``, ``scale`` or ``raw``; trinary by default).
- A pixel's grey level v is the mean of its colour channels (alpha aside); its occupancy is
  p = (255 - v) / 255, or v / 255 with ``negate``. Trinary: p > occupied_thresh is occupied (1),
  p < free_thresh is free (0), anything between is unknown. Scale: the same, except that a pixel
  between the thresholds keeps the value 1 + 98 (p - free) / (occ - free) percent, and is unknown
  only where the image's alpha is below 255. Raw: v is the occupancy in percent (0-100), other
  values are unknown.
- The image's first row is the top of the map (largest y): rows are flipped on reading.
- An ``OccupancyGrid`` holds int8 occupancy percent, -1 for unknown, row 0 at the lowest y.

Examples
--------
A map written as map_server files and read back, unchanged:

>>> import os, tempfile
>>> import numpy as np
>>> from taichi_match import GridMap
>>> from taichi_match.io import load_map, write_ros_map
>>> prob = np.full((20, 20), np.nan)
>>> prob[2:18, 2:18] = 0.0
>>> prob[2, 2:18] = 1.0
>>> grid = GridMap(prob, 0.05, origin=(-0.5, -0.5, 0.0))
>>> with tempfile.TemporaryDirectory() as folder:
...     write_ros_map(grid, os.path.join(folder, "map.yaml"))
...     back = load_map(os.path.join(folder, "map.yaml"))
>>> np.array_equal(back.prob, grid.prob, equal_nan=True), back.corner_pose
(True, (-0.5, -0.5, 0.0))
"""

import contextlib
import functools
import os
import signal
import stat
import tempfile
import threading
import warnings
import zipfile
import zlib
from io import BytesIO as io_bytes
from typing import Any

import numpy as np
import numpy.typing as npt

from ._errors import InvalidOptionError, MapFileError, MapFormatError, shown
from ._grid import GridMap

__all__ = [
    "read_ros_map", "write_ros_map", "read_image", "write_image", "to_occupancy_grid", "from_occupancy_grid",
    "save_npz", "load_npz", "save_npy", "load_npy", "load_map", "ros_map_paths", "MAX_MAP_CELLS", "MAX_FILE_BYTES",
    "MAX_YAML_BYTES",
]

MODES = ("trinary", "scale", "raw")
# Limits on what a map file may hold, checked before anything of that size is read or inflated:
MAX_MAP_CELLS = 2**28          # cells of a map read from a file (16384 x 16384; its float64 copy is 2 GiB)
MAX_FILE_BYTES = 2**31         # bytes of an image or array file
MAX_YAML_BYTES = 2**20         # bytes of a map's YAML

PathLike = str | os.PathLike          # a file's path, as the functions below take it


# ---------------------------------------------------------------------------------------------
# ROS map_server YAML

# A map's cell side (metres) must lie within these: beyond them the grid's coordinates overflow or
# a map of a few pixels spans more cells than a machine holds.
MIN_RESOLUTION, MAX_RESOLUTION = 1e-6, 1e4


def read_ros_map(yaml_path: PathLike, *, occupied_thresh: float | None = None,
                 free_thresh: float | None = None, negate: bool | None = None, mode: str | None = None,
                 resolution: float | None = None) -> GridMap:
    r"""Load a ROS ``map_server`` map (YAML + image) by map_server's rules (module docstring).

    Parameters
    ----------
    yaml_path : str or os.PathLike
        The map's YAML; its ``image`` is found relative to the YAML's folder.
    occupied_thresh, free_thresh, negate, mode, resolution : optional
        Override the YAML's fields (for maps whose thresholds or resolution are known to be off;
        see ``shared/maps/SOURCES.md``); None: the YAML's value, or map_server's default (0.65,
        0.196, 0, "trinary").

    Returns
    -------
    GridMap
        Row 0 at the lowest y (the image's last row), ``origin`` = the YAML's [x, y, yaw].

    Raises
    ------
    MapFileError
        If the YAML or image cannot be read, is not a regular file or is above ``MAX_YAML_BYTES``
        or ``MAX_FILE_BYTES``.
    MapFormatError
        If a field is missing or invalid, or the image is not one map_server reads or is larger
        than ``MAX_MAP_CELLS``.
    ImportError
        Without PyYAML or Pillow (the ``maps`` extra).

    Examples
    --------
    A map_server map of 3 x 2 pixels written by hand: black is occupied, white free, grey (205)
    unknown, and the image's first row is the top of the map:

    >>> import os, tempfile
    >>> import numpy as np
    >>> from taichi_match.io import read_ros_map, write_image
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     write_image(os.path.join(folder, "lab.pgm"), np.array([[0, 205], [254, 0], [254, 254]], np.uint8))
    ...     with open(os.path.join(folder, "lab.yaml"), "w") as f:
    ...         _ = f.write("image: lab.pgm\nresolution: 0.05\norigin: [-1.0, 2.0, 0.0]\n")
    ...     grid = read_ros_map(os.path.join(folder, "lab.yaml"))
    >>> grid.prob.tolist()
    [[0.0, 0.0], [0.0, 1.0], [1.0, nan]]
    >>> grid.resolution, grid.corner_pose
    (0.05, (-1.0, 2.0, 0.0))
    """
    meta = read_map_yaml(yaml_path)
    for key, value in (("occupied_thresh", occupied_thresh), ("free_thresh", free_thresh), ("negate", negate),
                       ("mode", mode), ("resolution", resolution)):
        if value is not None:
            meta[key] = value
    _check_meta(meta, yaml_path)
    image = read_image(meta["image"])
    occupancy = _pixels_to_occupancy(image, meta)
    prob = np.where(occupancy < 0, np.nan, occupancy / 100.0)[::-1]      # first image row = top of the map
    return GridMap(prob, meta["resolution"], tuple(meta["origin"]))


def read_map_yaml(yaml_path: PathLike) -> dict[str, Any]:
    """The fields of a map_server YAML as a dict, with ``image`` resolved against the YAML's folder
    (PyYAML's ``safe_load``: block and flow style, comments, anchors)."""
    yaml = _yaml()
    data = _read_bounded(yaml_path, MAX_YAML_BYTES, "map YAML")
    try:
        meta = yaml.load(data.decode("utf-8"), Loader=_unique_key_loader(yaml))
    except UnicodeDecodeError as exc:
        raise MapFormatError(f"{yaml_path}: not a text YAML file ({exc})") from exc
    except yaml.YAMLError as exc:
        raise MapFormatError(f"{yaml_path}: not valid YAML ({' '.join(str(exc).split())})") from exc
    except RecursionError as exc:
        raise MapFormatError(f"{yaml_path}: not map_server YAML (nested too deeply)") from exc
    if not isinstance(meta, dict):
        raise MapFormatError(f"{yaml_path}: expected 'key: value' fields (image, resolution, origin, ...); got "
                             f"{type(meta).__name__}")
    for key in ("image", "resolution", "origin"):
        if key not in meta:
            raise MapFormatError(f"{yaml_path}: the field {key!r} is missing (map_server needs image, "
                                 f"resolution and origin)")
    if not isinstance(meta["image"], str) or not meta["image"]:
        raise MapFormatError(f"{yaml_path}: 'image' must be a file name; got {shown(meta['image'])}")
    meta["image"] = os.path.join(os.path.dirname(os.path.abspath(yaml_path)), meta["image"])
    meta.setdefault("negate", 0)
    meta.setdefault("occupied_thresh", 0.65)
    meta.setdefault("free_thresh", 0.196)
    meta.setdefault("mode", "trinary")
    return meta


def _yaml():
    try:
        import yaml
    except ImportError as exc:                   # pragma: no cover - depends on the installation
        raise ImportError("map_server maps need PyYAML and Pillow: pip install 'taichi-match[maps]'") from exc
    return yaml


@functools.lru_cache(maxsize=None)
def _unique_key_loader(yaml):
    """PyYAML's safe loader, refusing a mapping that names a key twice (``safe_load`` keeps the
    last silently: a map file with two resolutions is ambiguous, not the second one)."""

    class UniqueKeyLoader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            seen = set()
            for key_node, _ in node.value:            # the keys as written (merges ``<<`` come later)
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=deep)
                try:
                    duplicate = key in seen
                except TypeError:                     # unhashable: the safe loader says so itself
                    continue
                if duplicate:
                    raise yaml.constructor.ConstructorError(None, None, f"the key {key!r} appears twice",
                                                            key_node.start_mark)
                seen.add(key)
            return super().construct_mapping(node, deep)

    return UniqueKeyLoader


def _pillow():
    try:
        from PIL import Image
    except ImportError as exc:                   # pragma: no cover - depends on the installation
        raise ImportError("map images need Pillow: pip install 'taichi-match[maps]'") from exc
    return Image


def _as_number(value):
    """A YAML scalar as map_server's parser reads a number: YAML 1.1 (PyYAML) leaves ``1e-3``, a
    float without a dot, a string, which yaml-cpp reads as a double."""
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def _check_meta(meta, path):
    def number(key, low=None, high=None, strict_low=False):
        value = _as_number(meta[key])
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise MapFormatError(f"{path}: {key!r} must be a number; got {shown(value)}")
        if low is not None and (value < low or (strict_low and value == low)) or high is not None and value > high:
            raise MapFormatError(f"{path}: {key!r} = {value} is out of range ({low} to {high})")
        return float(value)

    meta["resolution"] = number("resolution", MIN_RESOLUTION, MAX_RESOLUTION)
    meta["occupied_thresh"] = number("occupied_thresh", 0.0, 1.0)
    meta["free_thresh"] = number("free_thresh", 0.0, 1.0)
    if meta["free_thresh"] > meta["occupied_thresh"]:
        raise MapFormatError(f"{path}: free_thresh {meta['free_thresh']} is above occupied_thresh "
                             f"{meta['occupied_thresh']}")
    origin = meta["origin"]
    origin = [_as_number(v) for v in origin] if isinstance(origin, list) else origin
    if not isinstance(origin, list) or len(origin) not in (2, 3) or \
            not all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in origin):
        raise MapFormatError(f"{path}: 'origin' must be [x, y, yaw] numbers; got {shown(origin)}")
    meta["origin"] = [float(v) for v in origin] + ([0.0] if len(origin) == 2 else [])
    negate = meta["negate"]
    if negate not in (0, 1, True, False):
        raise MapFormatError(f"{path}: 'negate' must be 0 or 1; got {shown(negate)}")
    meta["negate"] = bool(negate)
    if meta["mode"] not in MODES:
        raise MapFormatError(f"{path}: 'mode' must be one of {MODES}; got {shown(meta['mode'])}")


def _pixels_to_occupancy(image, meta):
    """map_server's rules: int occupancy percent per pixel, -1 for unknown (image row order)."""
    pixels = image.astype(np.float64)
    has_alpha = pixels.ndim == 3 and pixels.shape[2] in (2, 4)
    alpha = pixels[..., -1] if has_alpha else None
    colour = pixels[..., :-1] if has_alpha else pixels
    grey = colour.mean(axis=2) if colour.ndim == 3 else colour
    if meta["mode"] == "raw":
        v = np.rint(grey).astype(np.int64)
        return np.where(v <= 100, v, -1)
    if meta["negate"]:
        grey = 255.0 - grey
    occ = (255.0 - grey) / 255.0
    out = np.full(grey.shape, -1, dtype=np.int64)
    between = (occ <= meta["occupied_thresh"]) & (occ >= meta["free_thresh"])
    if meta["mode"] == "scale":
        opaque = np.ones(grey.shape, bool) if alpha is None else alpha >= 255
        span = max(meta["occupied_thresh"] - meta["free_thresh"], 1e-12)
        scaled = np.rint(1 + 98 * (occ - meta["free_thresh"]) / span).astype(np.int64)
        out = np.where(between & opaque, scaled, out)
    out[occ > meta["occupied_thresh"]] = 100
    out[occ < meta["free_thresh"]] = 0
    return out


def write_ros_map(grid: GridMap, yaml_path: PathLike, *, image: str | None = None, mode: str = "trinary",
                  occupied_thresh: float = 0.65, free_thresh: float = 0.196) -> None:
    """Save ``grid`` as a map_server YAML and image (PGM, or PNG by the image name's extension).

    ``trinary``: occupied (p > occupied_thresh) black, free (p < free_thresh) white (254),
    unknown grey (205). ``scale``: grey levels 255 (1 - p), unknown transparent (PNG only).
    ``raw``: the occupancy percent as the grey level, unknown 255.

    The image is named after the YAML (``map.yaml`` -> ``map.pgm``) unless ``image`` is given; the
    YAML's name must end in .yaml or .yml, so the two never clash. Both files are written whole to
    temporary files beside them and then renamed over the old ones, image first, with SIGINT,
    SIGTERM and SIGHUP held back meanwhile (in the main thread; the signal is delivered once both
    are in place): an interruption leaves the complete old map or the complete new one.

    Parameters
    ----------
    grid : GridMap
        The map; its ``corner_pose`` becomes the YAML's ``origin``.
    yaml_path : str or os.PathLike
        NAME.yaml or NAME.yml.
    image : str, optional
        The image's file name, relative to the YAML's folder; default NAME.pgm (NAME.png in scale
        mode).
    mode : {"trinary", "scale", "raw"}
        map_server's ``mode``, written to the YAML.
    occupied_thresh, free_thresh : float
        The thresholds, written to the YAML and used for trinary pixels.

    Raises
    ------
    InvalidOptionError
        For an unknown ``mode``, or scale mode with an image that is not PNG.
    MapFileError
        If the YAML is not named .yaml/.yml, or a file cannot be written.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from taichi_match import GridMap
    >>> from taichi_match.io import read_ros_map, write_ros_map
    >>> grid = GridMap([[0.0, 1.0], [np.nan, 0.37]], 0.1, origin=(2.0, 0.0, 0.5))
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     write_ros_map(grid, os.path.join(folder, "map.yaml"))          # trinary: 0.37 is unknown
    ...     write_ros_map(grid, os.path.join(folder, "raw.yaml"), mode="raw")
    ...     files = sorted(os.listdir(folder))
    ...     trinary = read_ros_map(os.path.join(folder, "map.yaml"))
    ...     raw = read_ros_map(os.path.join(folder, "raw.yaml"))
    >>> files
    ['map.pgm', 'map.yaml', 'raw.pgm', 'raw.yaml']
    >>> trinary.prob.tolist(), raw.prob.tolist(), raw.corner_pose
    ([[0.0, 1.0], [nan, nan]], [[0.0, 1.0], [nan, 0.37]], (2.0, 0.0, 0.5))
    """
    if mode not in MODES:
        raise InvalidOptionError(f"mode must be one of {MODES}; got {mode!r}")
    yaml_path, image_path = ros_map_paths(yaml_path, mode, image)
    image = os.path.relpath(image_path, os.path.dirname(os.path.abspath(yaml_path)))    # as the YAML names it
    p = grid.prob[::-1]                                           # top row first
    unknown = np.isnan(p)
    q = np.nan_to_num(p, nan=0.0)
    if mode == "trinary":
        pixels = np.where(q > occupied_thresh, 0, np.where(q < free_thresh, 254, 205)).astype(np.uint8)
        pixels[unknown] = 205
    elif mode == "raw":
        pixels = np.where(unknown, 255, np.rint(100 * q)).astype(np.uint8)
    else:
        if not image.lower().endswith(".png"):
            raise InvalidOptionError("scale mode stores unknown cells as transparency: use a .png image")
        grey = np.rint(255 * (1 - q)).astype(np.uint8)
        pixels = np.dstack([grey, np.where(unknown, 0, 255).astype(np.uint8)])
    fields = {"image": image, "resolution": float(grid.resolution), "origin": [float(v) for v in grid.corner_pose],
              "negate": 0, "occupied_thresh": float(occupied_thresh), "free_thresh": float(free_thresh), "mode": mode}
    text = _yaml().safe_dump(fields, sort_keys=False, default_flow_style=None)
    _replace_files([(image_path, _image_bytes(image_path, pixels)), (yaml_path, text.encode("utf-8"))])


def ros_map_paths(yaml_path: PathLike, mode: str = "trinary", image: str | None = None) -> tuple[str, str]:
    """(YAML path, image path) that ``write_ros_map`` writes: the image is named after the YAML
    (``map.yaml`` -> ``map.pgm``, ``.png`` in scale mode) unless ``image`` is given, beside it.
    The YAML's name must end in .yaml or .yml, so the two never clash.

    Raises
    ------
    MapFileError
        If the YAML's name does not end in .yaml or .yml, or the image would be the YAML itself.

    Examples
    --------
    >>> import os
    >>> from taichi_match.io import ros_map_paths
    >>> yaml_path, image_path = ros_map_paths("maps/lab.yaml", mode="scale")
    >>> yaml_path, os.path.relpath(image_path)
    ('maps/lab.yaml', 'maps/lab.png')
    """
    yaml_path = os.fspath(yaml_path)
    base, ext = os.path.splitext(os.path.basename(yaml_path))
    if ext.lower() not in (".yaml", ".yml") or not base:
        raise MapFileError(f"the map's YAML must be named NAME.yaml or NAME.yml; got {yaml_path!r}")
    image_path = os.path.join(os.path.dirname(os.path.abspath(yaml_path)),
                              image or base + (".png" if mode == "scale" else ".pgm"))
    if os.path.abspath(image_path) == os.path.abspath(yaml_path):
        raise MapFileError(f"the image and the YAML would be the same file: {yaml_path!r}")
    return yaml_path, image_path


def _replace_files(contents):
    """Write each (path, bytes) to a temporary file beside it, then rename them over the paths in
    order, signals held back (``_signals_held``); on any failure the temporary files go."""
    for path, _ in contents:                     # before anything is written: all or nothing
        if os.path.lexists(path) and not os.path.isfile(path):
            raise MapFileError(f"cannot write {path!r}: it exists and is not a regular file")
    temporary = []
    try:
        with _signals_held():
            try:
                for path, data in contents:
                    temporary.append(_temporary_copy(path, data))
                for (path, _), tmp in zip(contents, temporary):
                    os.replace(tmp, path)
            finally:                             # before a held-back signal is delivered
                for tmp in temporary:
                    if os.path.exists(tmp):
                        os.unlink(tmp)
    except OSError as exc:
        raise MapFileError(f"cannot write {exc.filename or contents[0][0]!r}: {exc.strerror or exc}") from exc


def _temporary_copy(path, data):
    folder, name = os.path.split(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=folder)
    try:
        os.fchmod(fd, 0o666 & ~_umask())             # as open() would make it (mkstemp: 0600)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        os.unlink(tmp)
        raise
    return tmp


def _umask():
    """The process's umask (read by setting it, then put back at once)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def _signals_held(signums=("SIGINT", "SIGTERM", "SIGHUP")):
    """Hold these signals back while the block runs (Python handlers run in the main thread only,
    so elsewhere nothing is held), then deliver the first one that came, to the old handler."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    old = {}
    for name in signums:
        if hasattr(signal, name):
            sig = getattr(signal, name)
            old[sig] = signal.signal(sig, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        if caught:
            os.kill(os.getpid(), caught[0])


class _Signalled(BaseException):
    """A terminating signal raised as an exception, so that cleanups run (``_signals_raised``)."""


@contextlib.contextmanager
def _signals_raised(signums=("SIGTERM", "SIGHUP")):
    """While the block runs, these signals (where they would end the process: default handler)
    raise an exception instead, so that its ``finally`` clauses run (temporary files removed);
    then the signal is delivered as it would have been. Main thread only, as ``_signals_held``."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def raised(signum, frame):
        raise _Signalled(signum)

    old = {}
    for name in signums:
        sig = getattr(signal, name, None)
        if sig is not None and signal.getsignal(sig) is signal.SIG_DFL:
            old[sig] = signal.signal(sig, raised)
    try:
        yield
    except _Signalled as exc:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        old = {}
        os.kill(os.getpid(), exc.args[0])            # the default: the process ends here
        raise SystemExit(128 + exc.args[0]) from None
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


# ---------------------------------------------------------------------------------------------
# Images (Pillow): the formats map_server's SDL_image reads


IMAGE_FORMATS = ("PNG", "PPM", "BMP", "TIFF", "JPEG", "GIF")      # Pillow's names; PPM holds PGM


def read_image(path: PathLike) -> np.ndarray:
    """An image as a uint8 array (rows, cols) or (rows, cols, channels), first row at the top:
    grey, grey + alpha, RGB or RGBA as stored; palettes expanded; 16-bit levels scaled to 8 bits.
    Its size is checked against ``MAX_MAP_CELLS`` from the header, before the pixels are decoded.

    Raises
    ------
    MapFileError
        If the file cannot be read, is not a regular file or is above ``MAX_FILE_BYTES``.
    MapFormatError
        If it is not an image map_server reads (PGM, PNG, BMP, TIFF, JPEG, GIF), is damaged, or is
        larger than ``MAX_MAP_CELLS``.

    Examples
    --------
    See ``write_image``.
    """
    Image = _pillow()
    data = _read_bounded(path, MAX_FILE_BYTES, "image")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)     # our own limit is checked
            with Image.open(io_bytes(data), formats=IMAGE_FORMATS) as image:
                _check_size(*image.size, path)
                image.load()
                return _pixels(image)
    except MapFormatError:
        raise
    except Image.UnidentifiedImageError as exc:
        raise MapFormatError(f"{path}: not an image map_server reads (PGM, PNG, BMP, TIFF, JPEG, GIF)") from exc
    except MemoryError:
        raise
    except Exception as exc:       # Pillow's decoders on a damaged file: OSError, SyntaxError, ValueError, ...
        raise MapFormatError(f"{path}: a truncated, corrupt or unsupported image "
                             f"({type(exc).__name__}: {exc})") from exc


def _pixels(image):
    """A decoded Pillow image as ``read_image`` returns it."""
    if image.mode in ("I", "I;16", "I;16B", "I;16L", "F"):                    # 16-bit grey (PGM, PNG)
        levels = np.asarray(image, dtype=np.float64)
        return np.clip(np.rint(levels * (255.0 / 65535.0)), 0, 255).astype(np.uint8)
    if image.mode not in ("L", "LA", "RGB", "RGBA"):
        transparent = image.mode in ("PA", "RGBa", "La") or "transparency" in image.info
        image = image.convert("RGBA" if transparent else ("L" if image.mode == "1" else "RGB"))
    return np.array(image, dtype=np.uint8)


def _read_bounded(path, limit, what):
    """The bytes of ``path``, a regular file of at most ``limit`` bytes (a FIFO, a device or a
    directory is refused before it is opened: reading one could block or never end)."""
    try:
        info = os.stat(path)
        if not stat.S_ISREG(info.st_mode):
            raise MapFileError(f"cannot read {what} {os.fspath(path)!r}: not a regular file")
        if info.st_size > limit:
            raise MapFileError(f"cannot read {what} {os.fspath(path)!r}: {info.st_size} bytes, more than the "
                               f"limit of {limit}")
        with open(path, "rb") as f:
            data = f.read(info.st_size + 1)      # (a read of limit + 1 would allocate that much first)
    except MapFileError:
        raise
    except OSError as exc:
        raise MapFileError(f"cannot read {what} {os.fspath(path)!r}: {exc.strerror or exc}") from exc
    if len(data) > info.st_size:
        raise MapFileError(f"cannot read {what} {os.fspath(path)!r}: it grew while it was read")
    return data


def _check_size(width, height, path):
    if width * height > MAX_MAP_CELLS:
        raise MapFormatError(f"{path}: a {width} x {height} image is larger than the limit of {MAX_MAP_CELLS} cells")


def write_image(path: PathLike, pixels: npt.ArrayLike) -> None:
    """Save a uint8 image (rows, cols) or (rows, cols, 2|3|4): PGM (P5, grey only) or PNG (by the
    name's extension), replacing any old file whole (see ``write_ros_map``).

    Raises
    ------
    InvalidOptionError
        For a PGM with channels, or an array of another shape.
    MapFileError
        If the file cannot be written.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from taichi_match.io import read_image, write_image
    >>> grey_alpha = np.dstack([[[0, 128], [254, 255]], [[255, 255], [0, 255]]]).astype(np.uint8)
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     write_image(os.path.join(folder, "m.png"), grey_alpha)
    ...     back = read_image(os.path.join(folder, "m.png"))
    >>> back.shape, np.array_equal(back, grey_alpha)
    ((2, 2, 2), True)
    """
    _replace_files([(os.fspath(path), _image_bytes(os.fspath(path), pixels))])


def _image_bytes(path, pixels):
    pixels = np.ascontiguousarray(pixels, dtype=np.uint8)
    pgm = path.lower().endswith(".pgm")
    if pgm and pixels.ndim != 2:
        raise InvalidOptionError("a PGM image is grey only")
    if not (pixels.ndim == 2 or pixels.ndim == 3 and pixels.shape[2] in (2, 3, 4)):
        raise InvalidOptionError(f"an image is (rows, cols) or (rows, cols, 2|3|4); got shape {pixels.shape}")
    out = io_bytes()
    _pillow().fromarray(pixels).save(out, format="PPM" if pgm else "PNG")
    return out.getvalue()


# ---------------------------------------------------------------------------------------------
# OccupancyGrid-style arrays and NumPy files


def to_occupancy_grid(grid: GridMap) -> tuple[np.ndarray, dict[str, Any]]:
    """(data, info): int8 occupancy percent (rows, cols), -1 unknown, row 0 at the lowest y, and
    a dict with resolution, width, height and origin (x, y, yaw), as ``nav_msgs/OccupancyGrid``.

    Probabilities are rounded to whole percent. ``from_occupancy_grid`` takes ``data`` back (or
    ``data.ravel()`` with ``width`` and ``height``, as the message holds it).

    Examples
    --------
    >>> import numpy as np
    >>> from taichi_match import GridMap
    >>> from taichi_match.io import from_occupancy_grid, to_occupancy_grid
    >>> grid = GridMap([[0.0, 0.256], [np.nan, 1.0]], 0.05, origin=(1.0, 2.0))
    >>> data, info = to_occupancy_grid(grid)
    >>> data.tolist(), info
    ([[0, 26], [-1, 100]], {'resolution': 0.05, 'width': 2, 'height': 2, 'origin': (1.0, 2.0, 0.0)})
    >>> back = from_occupancy_grid(data.ravel(), info["resolution"], info["origin"],
    ...                            width=info["width"], height=info["height"])
    >>> back.prob.tolist()
    [[0.0, 0.26], [nan, 1.0]]
    """
    p = grid.prob
    data = np.where(np.isnan(p), -1, np.rint(100 * np.nan_to_num(p))).astype(np.int8)
    rows, cols = p.shape
    return data, {"resolution": grid.resolution, "width": cols, "height": rows, "origin": grid.corner_pose}


def from_occupancy_grid(data: npt.ArrayLike, resolution: float, origin: npt.ArrayLike = (0.0, 0.0, 0.0), *,
                        width: int | None = None, height: int | None = None) -> GridMap:
    """A GridMap from OccupancyGrid data: int8 percent (-1 unknown), flat row-major with ``width``
    and ``height``, or already (rows, cols).

    Parameters
    ----------
    data : array_like of int
        Occupancy percent 0..100, -1 unknown, row 0 at the lowest y; flat (``width`` * ``height``)
        or 2-D (rows, cols).
    resolution : float
        Cell side, metres.
    origin : (x, y) or (x, y, yaw)
        The message's ``info.origin`` as a 2-D pose (see ``GridMap``).
    width, height : int, optional
        Columns and rows, needed for flat data.

    Returns
    -------
    GridMap

    Raises
    ------
    MapFormatError
        If flat data does not hold ``width`` * ``height`` values, or a value is outside -1..100.

    Examples
    --------
    See ``to_occupancy_grid``.
    """
    arr = np.asarray(data)
    if arr.ndim == 1:
        if width is None or height is None or arr.size != width * height:
            raise MapFormatError(f"flat OccupancyGrid data needs width * height = {arr.size} cells")
        arr = arr.reshape(height, width)
    arr = arr.astype(np.int64)
    if arr.size and (arr.min() < -1 or arr.max() > 100):
        raise MapFormatError(f"OccupancyGrid values must be -1 or 0..100; got {arr.min()}..{arr.max()}")
    return GridMap(np.where(arr < 0, np.nan, arr / 100.0), resolution, origin)


def save_npz(grid: GridMap, path: PathLike) -> None:
    """Save probabilities, resolution and corner pose in a NumPy .npz file (compressed).

    Raises
    ------
    MapFileError
        If the file cannot be written.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from taichi_match import GridMap
    >>> from taichi_match.io import load_npz, save_npz
    >>> grid = GridMap([[0.25, np.nan], [1.0, 0.0]], 0.05, origin=(1.0, 2.0, 0.5))
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     save_npz(grid, os.path.join(folder, "map.npz"))
    ...     back = load_npz(os.path.join(folder, "map.npz"))
    >>> back.prob.tolist(), back.resolution, back.corner_pose       # exact, grey levels included
    ([[0.25, nan], [1.0, 0.0]], 0.05, (1.0, 2.0, 0.5))
    """
    try:
        np.savez_compressed(path, prob=grid.prob, resolution=grid.resolution, origin=np.array(grid.corner_pose))
    except OSError as exc:
        raise MapFileError(f"cannot write {path!r}: {exc.strerror or exc}") from exc


def load_npz(path: PathLike) -> GridMap:
    """Load a map saved by ``save_npz``.

    The arrays' sizes are checked against ``MAX_MAP_CELLS`` before they are inflated; pickles are
    refused.

    Raises
    ------
    MapFileError
        If the file cannot be read, is not a regular file or is above ``MAX_FILE_BYTES``.
    MapFormatError
        If it is not a map written by ``save_npz``.

    Examples
    --------
    See ``save_npz``.
    """
    data = _read_bounded(path, MAX_FILE_BYTES, "map")
    try:
        with zipfile.ZipFile(io_bytes(data)) as archive:
            for name in archive.namelist():          # the arrays' declared sizes, before inflating them
                with archive.open(name) as member:
                    version = np.lib.format.read_magic(member)
                    if version not in ((1, 0), (2, 0)):
                        raise MapFormatError(f"{path}: unsupported .npy version {version} in {name}")
                    read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                                   else np.lib.format.read_array_header_2_0)
                    shape, _, _ = read_header(member)
                if np.prod(shape, dtype=np.float64) > MAX_MAP_CELLS:
                    raise MapFormatError(f"{path}: an array of shape {shape}, more than the limit of "
                                         f"{MAX_MAP_CELLS} cells")
        with np.load(io_bytes(data), allow_pickle=False) as f:
            return GridMap(f["prob"], float(f["resolution"]), tuple(f["origin"]))
    except MapFormatError:
        raise
    except (KeyError, ValueError, TypeError, OSError, EOFError, zlib.error, zipfile.BadZipFile) as exc:
        raise MapFormatError(f"{path}: not a taichi_match .npz map ({type(exc).__name__}: {exc})") from exc


def save_npy(grid: GridMap, path: PathLike) -> None:
    """Save the OccupancyGrid-style int8 array (-1 unknown, 0..100, row 0 at the lowest y) in a .npy
    file; the resolution and origin are not stored (use ``save_npz`` to keep them).

    Raises
    ------
    MapFileError
        If the file cannot be written.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> from taichi_match import GridMap
    >>> from taichi_match.io import load_npy, save_npy
    >>> grid = GridMap([[0.25, np.nan], [1.0, 0.0]], 0.05, origin=(1.0, 2.0))
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     save_npy(grid, os.path.join(folder, "map.npy"))
    ...     back = load_npy(os.path.join(folder, "map.npy"), resolution=0.05, origin=(1.0, 2.0))
    >>> back.prob.tolist(), back.corner_pose
    ([[0.25, nan], [1.0, 0.0]], (1.0, 2.0, 0.0))
    """
    try:
        np.save(path, to_occupancy_grid(grid)[0])
    except OSError as exc:
        raise MapFileError(f"cannot write {path!r}: {exc.strerror or exc}") from exc


def load_npy(path: PathLike, *, resolution: float, origin: npt.ArrayLike = (0.0, 0.0, 0.0)) -> GridMap:
    """Load a .npy array: int8 occupancy percent (-1 unknown), or float probabilities (NaN unknown).

    Parameters
    ----------
    path : str or os.PathLike
        A .npy file holding a 2-D array, row 0 at the lowest y; integer arrays are read as
        OccupancyGrid percent (``from_occupancy_grid``), float arrays as probabilities.
    resolution : float
        Cell side, metres (not stored in the file).
    origin : (x, y) or (x, y, yaw)
        Corner pose of cell (0, 0) (not stored in the file).

    Raises
    ------
    MapFileError
        If the file cannot be read, is not a regular file or is above ``MAX_FILE_BYTES``.
    MapFormatError
        If it is not a NumPy array file, or holds values out of range.
    InvalidMapError
        If a float array is not a valid ``GridMap``.

    Examples
    --------
    See ``save_npy``.
    """
    data = _read_bounded(path, MAX_FILE_BYTES, "map")
    try:
        arr = np.load(io_bytes(data), allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise MapFormatError(f"{path}: not a NumPy array file ({exc})") from exc
    if np.issubdtype(arr.dtype, np.integer):
        return from_occupancy_grid(arr, resolution, origin)
    return GridMap(arr, resolution, origin)


def load_map(path: PathLike, **overrides: Any) -> GridMap:
    """Any supported map file by its extension: .yaml/.yml (map_server), .npz, or .npy (which needs
    ``resolution=`` and optionally ``origin=``).

    Parameters
    ----------
    path : str or os.PathLike
        The map file.
    **overrides
        For a YAML, ``read_ros_map``'s keyword arguments; for a .npy, ``resolution`` and
        ``origin``; ignored for a .npz.

    Raises
    ------
    MapFormatError
        For another extension, or a .npy without ``resolution``; and as the reader it calls.

    Examples
    --------
    See the module docstring; a .npy needs its geometry:

    >>> from taichi_match.io import load_map
    >>> load_map("scan.npy")
    Traceback (most recent call last):
        ...
    taichi_match._errors.MapFormatError: scan.npy: a .npy map needs its resolution (and origin) given separately
    """
    ext = os.path.splitext(str(path))[1].lower()
    if ext in (".yaml", ".yml"):
        return read_ros_map(path, **overrides)
    if ext == ".npz":
        return load_npz(path)
    if ext == ".npy":
        if "resolution" not in overrides:
            raise MapFormatError(f"{path}: a .npy map needs its resolution (and origin) given separately")
        return load_npy(path, resolution=overrides["resolution"], origin=overrides.get("origin", (0.0, 0.0, 0.0)))
    raise MapFormatError(f"{path}: unsupported map file (use a map_server .yaml, a .npz or a .npy)")
