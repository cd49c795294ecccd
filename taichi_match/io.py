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
"""

import contextlib
import os
import signal
import stat
import tempfile
import threading
import warnings
import zipfile
import zlib
from io import BytesIO as io_bytes

import numpy as np

from ._errors import InvalidOptionError, MapFileError, MapFormatError
from ._grid import GridMap

__all__ = [
    "read_ros_map", "write_ros_map", "read_image", "write_image", "to_occupancy_grid", "from_occupancy_grid",
    "save_npz", "load_npz", "save_npy", "load_npy", "load_map", "ros_map_paths", "MAX_MAP_CELLS", "MAX_FILE_BYTES", "MAX_YAML_BYTES",
]

MODES = ("trinary", "scale", "raw")
# Limits on what a map file may hold, checked before anything of that size is read or inflated:
MAX_MAP_CELLS = 2**28          # cells of a map read from a file (16384 x 16384; its float64 copy is 2 GiB)
MAX_FILE_BYTES = 2**31         # bytes of an image or array file
MAX_YAML_BYTES = 2**20         # bytes of a map's YAML


# ---------------------------------------------------------------------------------------------
# ROS map_server YAML


def read_ros_map(yaml_path, *, occupied_thresh=None, free_thresh=None, negate=None, mode=None,
                 resolution=None) -> GridMap:
    """Load a ROS ``map_server`` map. Keyword arguments override the YAML's fields (for maps whose
    thresholds or resolution are known to be off; see ``shared/maps/SOURCES.md``)."""
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


def read_map_yaml(yaml_path):
    """The fields of a map_server YAML as a dict, with ``image`` resolved against the YAML's folder
    (PyYAML's ``safe_load``: block and flow style, comments, anchors)."""
    yaml = _yaml()
    data = _read_bounded(yaml_path, MAX_YAML_BYTES, "map YAML")
    try:
        meta = yaml.safe_load(data.decode("utf-8"))
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
        raise MapFormatError(f"{yaml_path}: 'image' must be a file name; got {meta['image']!r}")
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
            raise MapFormatError(f"{path}: {key!r} must be a number; got {value!r}")
        if low is not None and (value < low or (strict_low and value == low)) or high is not None and value > high:
            raise MapFormatError(f"{path}: {key!r} = {value} is out of range")
        return float(value)

    meta["resolution"] = number("resolution", 0.0, strict_low=True)
    meta["occupied_thresh"] = number("occupied_thresh", 0.0, 1.0)
    meta["free_thresh"] = number("free_thresh", 0.0, 1.0)
    if meta["free_thresh"] > meta["occupied_thresh"]:
        raise MapFormatError(f"{path}: free_thresh {meta['free_thresh']} is above occupied_thresh "
                             f"{meta['occupied_thresh']}")
    origin = meta["origin"]
    origin = [_as_number(v) for v in origin] if isinstance(origin, list) else origin
    if not isinstance(origin, list) or len(origin) not in (2, 3) or \
            not all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in origin):
        raise MapFormatError(f"{path}: 'origin' must be [x, y, yaw] numbers; got {origin!r}")
    meta["origin"] = [float(v) for v in origin] + ([0.0] if len(origin) == 2 else [])
    negate = meta["negate"]
    if negate not in (0, 1, True, False):
        raise MapFormatError(f"{path}: 'negate' must be 0 or 1; got {negate!r}")
    meta["negate"] = bool(negate)
    if meta["mode"] not in MODES:
        raise MapFormatError(f"{path}: 'mode' must be one of {MODES}; got {meta['mode']!r}")


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


def write_ros_map(grid: GridMap, yaml_path, *, image=None, mode="trinary", occupied_thresh=0.65,
                  free_thresh=0.196):
    """Save ``grid`` as a map_server YAML and image (PGM, or PNG by the image name's extension).

    ``trinary``: occupied (p > occupied_thresh) black, free (p < free_thresh) white (254),
    unknown grey (205). ``scale``: grey levels 255 (1 - p), unknown transparent (PNG only).
    ``raw``: the occupancy percent as the grey level, unknown 255.

    The image is named after the YAML (``map.yaml`` -> ``map.pgm``) unless ``image`` is given; the
    YAML's name must end in .yaml or .yml, so the two never clash. Both files are written whole to
    temporary files beside them and then renamed over the old ones, image first, with SIGINT,
    SIGTERM and SIGHUP held back meanwhile (in the main thread; the signal is delivered once both
    are in place): an interruption leaves the complete old map or the complete new one.
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


def ros_map_paths(yaml_path, mode="trinary", image=None):
    """(YAML path, image path) that ``write_ros_map`` writes: the image is named after the YAML
    (``map.yaml`` -> ``map.pgm``, ``.png`` in scale mode) unless ``image`` is given, beside it.
    The YAML's name must end in .yaml or .yml, so the two never clash."""
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


# ---------------------------------------------------------------------------------------------
# Images (Pillow): the formats map_server's SDL_image reads


IMAGE_FORMATS = ("PNG", "PPM", "BMP", "TIFF", "JPEG", "GIF")      # Pillow's names; PPM holds PGM


def read_image(path):
    """An image as a uint8 array (rows, cols) or (rows, cols, channels), first row at the top:
    grey, grey + alpha, RGB or RGBA as stored; palettes expanded; 16-bit levels scaled to 8 bits.
    Its size is checked against ``MAX_MAP_CELLS`` from the header, before the pixels are decoded."""
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
        raise MapFormatError(f"{path}: a truncated, corrupt or unsupported image ({type(exc).__name__}: {exc})") from exc


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


def write_image(path, pixels):
    """Save a uint8 image (rows, cols) or (rows, cols, 2|3|4): PGM (P5, grey only) or PNG (by the
    name's extension), replacing any old file whole (see ``write_ros_map``)."""
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


def to_occupancy_grid(grid: GridMap):
    """(data, info): int8 occupancy percent (rows, cols), -1 unknown, row 0 at the lowest y, and
    a dict with resolution, width, height and origin (x, y, yaw), as ``nav_msgs/OccupancyGrid``."""
    p = grid.prob
    data = np.where(np.isnan(p), -1, np.rint(100 * np.nan_to_num(p))).astype(np.int8)
    rows, cols = p.shape
    return data, {"resolution": grid.resolution, "width": cols, "height": rows, "origin": grid.corner_pose}


def from_occupancy_grid(data, resolution, origin=(0.0, 0.0, 0.0), *, width=None, height=None) -> GridMap:
    """A GridMap from OccupancyGrid data: int8 percent (-1 unknown), flat row-major with ``width``
    and ``height``, or already (rows, cols)."""
    arr = np.asarray(data)
    if arr.ndim == 1:
        if width is None or height is None or arr.size != width * height:
            raise MapFormatError(f"flat OccupancyGrid data needs width * height = {arr.size} cells")
        arr = arr.reshape(height, width)
    arr = arr.astype(np.int64)
    if arr.size and (arr.min() < -1 or arr.max() > 100):
        raise MapFormatError(f"OccupancyGrid values must be -1 or 0..100; got {arr.min()}..{arr.max()}")
    return GridMap(np.where(arr < 0, np.nan, arr / 100.0), resolution, origin)


def save_npz(grid: GridMap, path):
    """Save probabilities, resolution and corner pose in a NumPy .npz file."""
    try:
        np.savez_compressed(path, prob=grid.prob, resolution=grid.resolution, origin=np.array(grid.corner_pose))
    except OSError as exc:
        raise MapFileError(f"cannot write {path!r}: {exc.strerror or exc}") from exc


def load_npz(path) -> GridMap:
    """Load a map saved by ``save_npz``."""
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


def save_npy(grid: GridMap, path):
    """Save the OccupancyGrid-style int8 array (-1 unknown, 0..100, row 0 at the lowest y) in a .npy
    file; the resolution and origin are not stored (use ``save_npz`` to keep them)."""
    try:
        np.save(path, to_occupancy_grid(grid)[0])
    except OSError as exc:
        raise MapFileError(f"cannot write {path!r}: {exc.strerror or exc}") from exc


def load_npy(path, *, resolution, origin=(0.0, 0.0, 0.0)) -> GridMap:
    """Load a .npy array: int8 occupancy percent (-1 unknown), or float probabilities (NaN unknown)."""
    data = _read_bounded(path, MAX_FILE_BYTES, "map")
    try:
        arr = np.load(io_bytes(data), allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise MapFormatError(f"{path}: not a NumPy array file ({exc})") from exc
    if np.issubdtype(arr.dtype, np.integer):
        return from_occupancy_grid(arr, resolution, origin)
    return GridMap(arr, resolution, origin)


def load_map(path, **overrides) -> GridMap:
    """Any supported map file by its extension: .yaml/.yml (map_server), .npz, or .npy (which needs
    ``resolution=`` and optionally ``origin=``)."""
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
