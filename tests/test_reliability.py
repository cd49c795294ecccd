"""Never lose a user's data, never leak a foreign exception (issue 11): the merge's outputs, the
atomic replacement of a map on disk, the command line's exit codes."""

import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from conftest import rasterize, room_scene

from taichi_match import MapFileError, TaichiMatchError, io
from taichi_match.cli import main


@pytest.fixture
def pair(tmp_path):
    a = rasterize(room_scene, (130, 170), 0.05, (-4.1, -3.1))
    b = rasterize(room_scene, (120, 160), 0.05, (-4.0, -3.0), pose_a2b=(0.15, -0.1, 0.05))
    io.write_ros_map(a, tmp_path / "a.yaml")
    io.write_ros_map(b, tmp_path / "b.yaml")
    return tmp_path / "a.yaml", tmp_path / "b.yaml"


def snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def merge(a, b, out, *extra):
    return main(["merge", str(a), str(b), "--pose", "0.15", "-0.1", "0.05", "-o", str(out), *extra])


# ---------------------------------------------------------------------------------------------
# 1. merge -o never writes over an input, never clashes, never replaces without --force


@pytest.mark.parametrize("target", ["a.yaml", "b.yaml", "a.pgm"])
def test_merge_refuses_to_write_over_an_input(pair, tmp_path, capsys, target):
    a, b = pair
    out = tmp_path / target
    if target == "a.pgm":                 # a YAML whose image would be A's image
        out = tmp_path / "a.yml"
    before = snapshot(tmp_path)
    assert merge(a, b, out, "--force") == 2
    assert "input" in capsys.readouterr().err
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("name", ["merged.pgm", "merged.png", "", "out/", ".", "merged"])
def test_merge_output_must_name_a_yaml_and_nothing_is_left_behind(pair, tmp_path, capsys, name):
    a, b = pair
    before = snapshot(tmp_path)
    out = str(tmp_path / name) if name else ""
    assert merge(a, b, out) == 2
    err = capsys.readouterr().err
    assert err.startswith("taichi-match: error:") and "Traceback" not in err
    assert snapshot(tmp_path) == before


def test_merge_replaces_an_existing_output_only_with_force(pair, tmp_path, capsys):
    a, b = pair
    out = tmp_path / "m.yaml"
    assert merge(a, b, out) == 0
    first = snapshot(tmp_path)
    assert merge(a, b, out) == 2 and "--force" in capsys.readouterr().err
    assert snapshot(tmp_path) == first
    assert merge(a, b, out, "--force") == 0
    assert io.read_ros_map(out).shape == io.read_ros_map(tmp_path / "m.yaml").shape
    assert sorted(snapshot(tmp_path)) == sorted(first)          # no stray temporary files


# ---------------------------------------------------------------------------------------------
# 2. an interrupted write leaves the old map or the new one, whole


def two_maps():
    old = rasterize(room_scene, (60, 80), 0.05, (-1.0, -1.0))
    new = rasterize(room_scene, (90, 70), 0.1, (-3.0, -2.0))
    return old, new


def same_map(grid, other):
    return (grid.shape == other.shape and grid.resolution == other.resolution and grid.origin == other.origin
            and np.array_equal(np.isnan(grid.prob), np.isnan(other.prob)))


@pytest.mark.parametrize("moment", range(6))
def test_a_signal_at_any_moment_of_the_write_is_delivered_after_it(tmp_path, monkeypatch, moment):
    # moments: before the image's temporary file, before the YAML's, before the image's rename,
    # after it (the new image beside the old YAML), before the YAML's rename, after both
    old, new = two_maps()
    path = tmp_path / "m.yaml"
    io.write_ros_map(old, path)
    calls = {"n": 0}

    def hook():
        if calls["n"] == moment:
            os.kill(os.getpid(), signal.SIGINT)
        calls["n"] += 1

    copy, replace = io._temporary_copy, os.replace

    def temporary_copy(*args):
        hook()
        return copy(*args)

    def replace_then_hook(*args):
        hook()
        replace(*args)
        hook()

    monkeypatch.setattr(io, "_temporary_copy", temporary_copy)
    monkeypatch.setattr(io.os, "replace", replace_then_hook)
    with pytest.raises(KeyboardInterrupt):
        io.write_ros_map(new, path)
        for _ in range(100):                     # the held-back signal arrives within a few bytecodes
            pass
    monkeypatch.undo()
    assert same_map(io.read_ros_map(path), new)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pgm", "m.yaml"]


@pytest.mark.parametrize("failing", [0, 1])
def test_a_failed_write_leaves_the_old_map_and_no_temporary_file(tmp_path, monkeypatch, failing):
    old, new = two_maps()
    path = tmp_path / "m.yaml"
    io.write_ros_map(old, path)
    before = snapshot(tmp_path)
    copy, calls = io._temporary_copy, {"n": 0}

    def temporary_copy(*args):
        calls["n"] += 1
        if calls["n"] - 1 == failing:
            raise OSError(28, "No space left on device")
        return copy(*args)

    monkeypatch.setattr(io, "_temporary_copy", temporary_copy)
    with pytest.raises(MapFileError, match="No space left"):
        io.write_ros_map(new, path)
    assert snapshot(tmp_path) == before


def test_sigterm_during_cli_merges_leaves_an_old_or_a_new_map(tmp_path):
    # a real process, killed by SIGTERM at several moments of repeated merges into one output
    a = rasterize(room_scene, (400, 500), 0.02, (-4.1, -3.1))
    b = rasterize(room_scene, (380, 480), 0.02, (-4.0, -3.0), pose_a2b=(0.15, -0.1, 0.05))
    io.write_ros_map(a, tmp_path / "a.yaml")
    io.write_ros_map(b, tmp_path / "b.yaml")
    out = tmp_path / "m.yaml"

    def script(*poses):
        return textwrap.dedent(f"""
            from taichi_match.cli import main
            for pose in {poses!r}:
                main(["merge", {str(tmp_path / "a.yaml")!r}, {str(tmp_path / "b.yaml")!r}, "--pose", pose, "-0.1",
                      "0.05", "-o", {str(out)!r}, "--force"])
        """)

    maps = []
    for pose in ("0.15", "3.15"):
        subprocess.run([sys.executable, "-c", script(pose)], check=True, capture_output=True, timeout=300)
        maps.append(io.read_ros_map(out))
    assert not same_map(*maps)
    for delay in (0.05, 0.3, 0.6, 0.9, 1.2, 1.5, 2.0, 2.5):
        proc = subprocess.Popen([sys.executable, "-c", script("0.15", "3.15", "0.15", "3.15")],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            proc.wait(timeout=delay)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)
        now = io.read_ros_map(out)                  # loads, and is one of the two maps
        assert same_map(now, maps[0]) or same_map(now, maps[1])
        assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pgm", "a.yaml", "b.pgm", "b.yaml", "m.pgm", "m.yaml"]


# ---------------------------------------------------------------------------------------------
# 3. exit codes: 130 on Ctrl-C, quiet on a closed pipe, one line for anything unexpected


@pytest.mark.parametrize("exc, code, says", [(KeyboardInterrupt(), 130, "interrupted"),
                                             (MemoryError(), 2, "out of memory"),
                                             (RecursionError("too deep"), 2, "RecursionError: too deep"),
                                             (OSError(5, "Input/output error"), 2, "Input/output error")])
def test_exit_codes_for_what_a_command_may_raise(pair, monkeypatch, capsys, exc, code, says):
    from taichi_match import cli

    def boom(args):
        raise exc

    monkeypatch.setattr(cli, "_align", boom)
    a, b = pair
    assert main(["align", str(a), str(b), "--initial", "0", "0", "0"]) == code
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err and err.count("\n") == 1


def test_a_closed_pipe_ends_the_command_quietly(pair):
    a, b = pair
    proc = subprocess.run(f"{sys.executable} -m taichi_match.cli align {a} {b} --initial 0 0 0 --json | head -c 1",
                          shell=True, capture_output=True, text=True, timeout=300)
    assert proc.stdout == "{" and "Traceback" not in proc.stderr and "Error" not in proc.stderr, proc.stderr


# ---------------------------------------------------------------------------------------------
# 4. hostile files: bounded reads, our own errors


def yaml_for(tmp_path, image, origin="[0.0, 0.0, 0.0]"):
    path = tmp_path / "m.yaml"
    path.write_text(f"image: {image}\nresolution: 0.05\norigin: {origin}\n")
    return path


def test_an_image_that_is_a_fifo_or_a_device_is_refused_without_reading(tmp_path):
    os.mkfifo(tmp_path / "fifo.pgm")
    script = textwrap.dedent(f"""
        from taichi_match import io, MapFileError
        for image in ({str(tmp_path / "fifo.pgm")!r}, "/dev/zero", "/dev/urandom"):
            meta = f"image: {{image}}\\nresolution: 0.05\\norigin: [0, 0, 0]\\n"
            (open({str(tmp_path / "m.yaml")!r}, "w")).write(meta)
            try:
                io.read_ros_map({str(tmp_path / "m.yaml")!r})
            except MapFileError as exc:
                assert "not a regular file" in str(exc), exc
            else:
                raise SystemExit("no error")
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr


def png_file(path, width, height, data, header_length=13):
    import struct
    import zlib

    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)[:header_length]
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", data) + chunk(b"IEND", b""))


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads VmHWM from /proc (Linux)")
def test_a_png_bomb_is_not_inflated_past_its_header(tmp_path):
    """1 GiB of zeros deflated into a 10 x 10 PNG: only what the header declares is inflated (read
    in a child process, whose peak memory is its own; Linux)."""
    import zlib

    bomb = zlib.compressobj(9)
    data = b"".join(bomb.compress(bytes(2**24)) for _ in range(64)) + bomb.flush()     # 1 GiB of zeros
    assert len(data) < 2**21
    png_file(tmp_path / "bomb.png", 10, 10, data)
    code = ("import sys\nfrom taichi_match import io\ntry:\n    image = io.read_image(sys.argv[1])\n"
            "    assert image.shape == (10, 10) and not image.any()\nexcept io.MapFormatError:\n    pass\n"
            "print(next(line.split()[1] for line in open('/proc/self/status') if line.startswith('VmHWM')))\n")
    run = subprocess.run([sys.executable, "-c", code, str(tmp_path / "bomb.png")], check=True, timeout=60,
                         capture_output=True, text=True)
    # VmHWM, the peak resident memory of this image (ru_maxrss would also count the forked parent's)
    peak = int(run.stdout.split()[-1]) * 1024
    assert peak < 2**29, peak


@pytest.mark.parametrize("case", ["ihdr", "huge", "p2-range", "p2-text", "deep-origin", "npz-cut", "npz-huge"])
def test_hostile_map_files_raise_our_errors(tmp_path, case):
    import zlib

    from taichi_match import MapFormatError, TaichiMatchError

    if case == "ihdr":
        png_file(tmp_path / "x.png", 4, 4, zlib.compress(bytes(20)), header_length=12)
        call = lambda: io.read_image(str(tmp_path / "x.png"))              # noqa: E731
    elif case == "huge":
        png_file(tmp_path / "x.png", 2**20, 2**20, zlib.compress(bytes(20)))
        call = lambda: io.read_image(str(tmp_path / "x.png"))              # noqa: E731
    elif case in ("p2-range", "p2-text"):
        body = b"0 255 300 1\n" if case == "p2-range" else b"0 a 3 1\n"
        (tmp_path / "x.pgm").write_bytes(b"P2\n2 2\n255\n" + body)
        call = lambda: io.read_image(str(tmp_path / "x.pgm"))              # noqa: E731
    elif case == "deep-origin":
        io.write_image(str(tmp_path / "x.pgm"), np.zeros((2, 2), np.uint8))
        path = yaml_for(tmp_path, "x.pgm", origin="[" * 100_000 + "0" + "]" * 100_000)
        call = lambda: io.read_ros_map(path)                               # noqa: E731
    elif case == "npz-cut":
        grid = rasterize(room_scene, (60, 80), 0.05, (-1.0, -1.0))
        io.save_npz(grid, tmp_path / "x.npz")
        data = (tmp_path / "x.npz").read_bytes()
        (tmp_path / "x.npz").write_bytes(data[: len(data) // 2])
        call = lambda: io.load_npz(tmp_path / "x.npz")                     # noqa: E731
    else:                                   # an .npz whose array header declares 2**40 cells
        import io as stdlib_io
        import zipfile
        buf = stdlib_io.BytesIO()
        np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": (2**20, 2**20)})
        with zipfile.ZipFile(tmp_path / "x.npz", "w", zipfile.ZIP_DEFLATED) as z:
            z.writestr("prob.npy", buf.getvalue() + bytes(64))
        call = lambda: io.load_npz(tmp_path / "x.npz")                     # noqa: E731
    with pytest.raises(TaichiMatchError) as info:
        call()
    assert isinstance(info.value, (MapFormatError, io.MapFileError)), info.value


# ---------------------------------------------------------------------------------------------
# 5. options and poses that imply absurd memory or overflow


def test_options_that_would_overflow_or_exhaust_memory_are_refused_or_cheap(pair):
    import taichi_match as tm
    from taichi_match import InvalidOptionError, InvalidPoseError
    from taichi_match.merge import merge_maps

    a, b = (io.read_ros_map(p) for p in pair)
    for bad in (dict(rotation_scale=1e300), dict(covariance_scale=0.0), dict(blur=1e300), dict(prior_weight=1e300)):
        with pytest.raises(InvalidOptionError):
            tm.MatchOptions(**bad)
    # a blur far wider than the map is cut at the map's extent: no 2.6 TiB kernel
    res = tm.match(a, b, (0.1, -0.1, 0.05), blur=1e6, blur_kind="gaussian", blur_growth=1.0)
    assert np.all(np.isfinite(res.pose))
    for pose in ((1e6, 0.0, 0.0), (1e300, 0.0, 0.0)):
        with pytest.raises(InvalidPoseError, match="merged map"):
            merge_maps(a, b, pose)


def test_a_masked_array_keeps_its_mask_as_unknown_cells():
    from taichi_match import GridMap

    prob = np.ma.array(np.full((3, 4), 0.2), mask=np.zeros((3, 4), bool))
    prob.mask[1, 2] = True
    grid = GridMap(prob, 0.1)
    assert np.isnan(grid.prob[1, 2]) and np.count_nonzero(np.isnan(grid.prob)) == 1


@pytest.mark.parametrize("args", [["--pose", "1e6", "0", "0"], ["--pose", "1e300", "0", "0"]])
def test_merge_with_an_absurd_pose_exits_2(pair, tmp_path, capsys, args):
    a, b = pair
    assert main(["merge", str(a), str(b), *args, "-o", str(tmp_path / "m.yaml")]) == 2
    err = capsys.readouterr().err
    assert "merged map" in err and "Traceback" not in err
    assert not (tmp_path / "m.yaml").exists()


def test_plot_must_name_a_picture_file(pair, tmp_path, capsys):
    a, b = pair
    assert main(["align", str(a), str(b), "--initial", "0.15", "-0.1", "0.05", "--plot", str(tmp_path)]) == 2
    assert ".png" in capsys.readouterr().err


@pytest.mark.parametrize("extra", [["--blur", "1e6"], ["--blur", "1e6", "--blur-kind", "gaussian"]])
def test_absurd_but_valid_options_give_a_reported_result_not_a_crash(pair, capsys, extra):
    a, b = pair
    code = main(["align", str(a), str(b), "--initial", "0.15", "-0.1", "0.05", *extra])
    captured = capsys.readouterr()
    assert code in (0, 1) and "Traceback" not in captured.err
    assert "ACCEPTED" in captured.out           # the verdict line


@pytest.mark.parametrize("extra", [["--resolution-a", "1e-9"], ["--resolution-a", "1e-9", "--blur-kind", "gaussian"],
                                   ["--resolution-b", "1e5"]])
def test_a_resolution_beyond_any_map_is_bad_input(pair, capsys, extra):
    """Cells of a nanometre or 100 km (outside 1e-6 to 1e4 m) are refused, saying which map."""
    a, b = pair
    assert main(["align", str(a), str(b), "--initial", "0.15", "-0.1", "0.05", *extra]) == 2
    err = capsys.readouterr().err
    assert "out of range" in err and "Traceback" not in err


def test_merge_into_an_existing_directory_name_exits_2(pair, tmp_path, capsys):
    a, b = pair
    (tmp_path / "out.yaml").mkdir()
    before = snapshot(tmp_path)
    assert merge(a, b, tmp_path / "out.yaml", "--force") == 2
    assert "Traceback" not in capsys.readouterr().err and snapshot(tmp_path) == before


def test_an_image_named_in_a_subfolder_is_written_there_and_named_so_in_the_yaml(tmp_path):
    (tmp_path / "images").mkdir()
    grid = rasterize(room_scene, (60, 80), 0.05, (-1.0, -1.0))
    io.write_ros_map(grid, tmp_path / "m.yaml", image="images/m.pgm")
    assert "image: images/m.pgm" in (tmp_path / "m.yaml").read_text()
    assert same_map(io.read_ros_map(tmp_path / "m.yaml"), grid)


def test_error_messages_show_numpy_scalars_as_plain_numbers():
    # NumPy 2's repr prints np.float64(nan): a message shows the number as the user typed it
    from taichi_match import GridMap, Matcher, MatchOptions
    from taichi_match.slam import SlamOptions

    a = GridMap(np.zeros((30, 30)), 0.1)
    calls = (lambda: Matcher().match(a, a, (0, 0, 0), search_window=(np.float64(np.nan), 1.0)),
             lambda: GridMap(np.zeros((3, 3)), np.float64(-0.1)),
             lambda: MatchOptions(blur=np.float64(-1.0)),
             lambda: MatchOptions(levels=np.int64(0)),
             lambda: SlamOptions(resolution=np.float64(-1.0)))
    for call in calls:
        with pytest.raises(TaichiMatchError) as info:
            call()
        assert "np." not in str(info.value) and "got" in str(info.value), str(info.value)
