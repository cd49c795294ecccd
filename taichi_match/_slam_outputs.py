"""The mapping loop's outputs (``slam.Slam``): ``trajectory.tum``, ``map.yaml`` + ``map.pgm``,
``graph.g2o`` and ``report.md`` in a folder, written together or not at all; and the run's summary
lines that the report and the command line share."""

import os

import numpy as np

from ._errors import InvalidOptionError, SlamRunError

__all__ = ["OUTPUTS", "output_paths", "write_outputs", "report", "loop_summary", "scan_times", "jump_summary"]

OUTPUTS = ("trajectory.tum", "map.yaml", "map.pgm", "graph.g2o", "report.md")


def output_paths(folder, *, force: bool = False, keep=()) -> dict:
    """The paths ``write_outputs`` writes in ``folder``, checked before any work: an existing output
    is an error without ``force``, and always when it is a folder or one of the files in ``keep``
    (the inputs: a log or a reference never becomes an output). Returns {name: Path}."""
    import tempfile
    from pathlib import Path

    if not isinstance(folder, (str, os.PathLike)):
        raise InvalidOptionError(f"the output folder must be a path (str or os.PathLike); got {type(folder).__name__}")
    if not str(folder).strip():
        raise InvalidOptionError("the output folder must be named (an empty path would write into the current "
                                 "folder)")
    name = os.fsdecode(folder)                  # bytes that are not UTF-8 come back as lone surrogates
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        raise InvalidOptionError(f"the output folder's name must be valid UTF-8 (gtsam writes graph.g2o through a "
                                 f"UTF-8 path); got {folder!r}") from None
    folder = Path(name)
    if folder.exists() and not folder.is_dir():
        raise FileExistsError(f"{folder} exists and is not a folder")
    existing = folder.absolute()
    while not existing.exists() and existing != existing.parent:      # the folder, or where it would go
        existing = existing.parent
    if not existing.is_dir():
        raise NotADirectoryError(f"cannot make the output folder {folder}: {existing} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):                      # (read-only file systems too)
        raise PermissionError(f"cannot write into {existing}: the outputs would be lost after the run")
    try:                                # what access() cannot tell (/proc, some mounts): a folder made and removed
        os.rmdir(tempfile.mkdtemp(prefix=".slam-probe-", dir=existing))
    except OSError as exc:
        raise PermissionError(f"cannot write into {existing} ({exc.strerror}): the outputs would be lost after "
                              f"the run") from None
    paths = {name: folder / file for name, file in zip(("trajectory", "map", "image", "graph", "report"), OUTPUTS)}
    kept = [Path(k).resolve() for k in keep if k]
    for path in paths.values():
        if path.resolve() in kept:
            raise FileExistsError(f"{path} is an input of this run; choose another output folder")
        if path.is_dir():
            raise FileExistsError(f"{path} is a folder")
        if path.exists() and not force:
            raise FileExistsError(f"{path} exists (use force=True / --force to replace the outputs)")
    return paths


def write_outputs(result, folder, *, source: str = "", force: bool = False, keep=(), notes=()) -> dict:
    """Write ``trajectory.tum``, ``map.yaml`` + ``map.pgm``, ``graph.g2o`` and ``report.md`` into
    ``folder`` (created if missing), after ``output_paths``'s checks. All five are written to a
    temporary folder inside ``folder`` first and then moved into place together, with SIGINT,
    SIGTERM and SIGHUP held back meanwhile: a failure leaves the old outputs, not a mix of old and
    new. ``notes``: lines for report.md about the input (``report``). Returns {name: path}."""
    import shutil
    import tempfile
    from pathlib import Path

    from . import io
    from ._pose_graph import import_gtsam
    from .logs import write_tum
    from .slam import SlamResult

    if not isinstance(result, SlamResult):
        raise InvalidOptionError(f"result must be a taichi_match.slam.SlamResult; got {type(result).__name__}")
    gtsam = import_gtsam()
    paths = output_paths(folder, force=force, keep=keep)
    folder = paths["report"].parent
    folder.mkdir(parents=True, exist_ok=True)
    with io._signals_raised():                    # SIGTERM, SIGHUP: the temporary folder removed first
        staging = Path(tempfile.mkdtemp(prefix=".slam-", dir=folder))
        try:
            staged = {name: staging / path.name for name, path in paths.items()}
            io.write_ros_map(result.map, staged["map"])
            write_tum(staged["trajectory"], result.timestamps, result.poses)
            _write_g2o(gtsam, result, staged["graph"])
            # (a log's name that is not UTF-8 is written escaped)
            staged["report"].write_text(report(result, source, notes), encoding="utf-8", errors="backslashreplace")
            with io._signals_held():
                for name, path in paths.items():
                    staged[name].replace(path)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    return paths


def _write_g2o(gtsam, result, path):
    """``graph.g2o`` by gtsam's writer, checked: it reports no error (a full disk or a file size
    limit cut the file short, silently), so the file must hold a line per node and per edge, each
    ended, and only finite numbers."""
    graph = _plain_graph(gtsam, result.graph)
    gtsam.writeG2o(graph, result.values, str(path))
    text = path.read_text(encoding="utf-8", errors="replace")
    lines = result.values.size() + graph.size()
    if text.count("\n") != lines or not text.endswith("\n"):
        raise OSError(f"gtsam wrote {path.name} in part ({text.count(chr(10))} of {lines} lines): is the disk full?")
    if any(word in ("nan", "-nan", "inf", "-inf") for word in text.lower().split()):
        raise SlamRunError(f"{path.name} would hold non-finite numbers: a covariance overflowed (check the options)")


def _plain_graph(gtsam, graph):
    """The graph's between-factors with their Gaussian noise (g2o has no robust kernels, no priors)."""
    plain = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        factor = graph.at(i)
        if isinstance(factor, gtsam.BetweenFactorPose2):
            noise = factor.noiseModel()
            if isinstance(noise, gtsam.noiseModel.Robust):
                noise = noise.noise()
            a, b = factor.keys()
            plain.add(gtsam.BetweenFactorPose2(a, b, factor.measured(), noise))
    return plain


def loop_summary(result) -> str:
    """The loop closures in one line: accepted of tried and in the graph, the loop-closing stage's
    and the audit's repairs (``audit``) apart, and those the final gate took out (``loop_gate``)."""
    def counts(loops):
        return (f"accepted {sum(lp['accepted'] for lp in loops)}/{len(loops)}, "
                f"in the graph {sum(lp['edge'] for lp in loops)}")

    repairs = [lp for lp in result.loops if lp.get("repair")]
    gated = sum(bool(lp.get("gated")) for lp in result.loops)
    text = f"loop closures {counts([lp for lp in result.loops if not lp.get('repair')])}"
    text += f"; the audit's repairs {counts(repairs)}" if repairs else ""
    gate = f"; {gated} taken out of the graph at the end, the optimised graph contradicting them (loop_gate)"
    return text + (gate if gated else "")


def scan_times(result) -> str:
    """Each scan's time as it came (``SlamResult.add_seconds``) in words: median, 99th percentile
    and maximum after the first match, which in a new process includes compiling Taichi's kernels
    (shown apart)."""
    times = 1e3 * np.asarray(result.add_seconds)
    if len(times) < 3:
        return f"at most {times.max():.0f} ms" if len(times) else ""
    median, high, top = np.percentile(times[2:], [50, 99, 100])
    return (f"median {median:.1f} ms, 99th percentile {high:.0f} ms, at most {top:.0f} ms (the first match, "
            f"which compiles Taichi's kernels in a new process: {times[1]:.0f} ms)")


def jump_summary(result) -> str:
    """The odometry jumps that a search found (``SlamOptions.jump_check``), in words."""
    jumps = [c["scan"] for c in result.jump_checks if c["jump"]]
    spikes = [c["scan"] - 1 for c in result.jump_checks if c.get("spike")]
    if not jumps:
        return "no odometry jump found"
    said = (f"the odometry jumps before scan{'s' if len(jumps) > 1 else ''} {', '.join(map(str, jumps))}: "
            f"bridged by a scan match, the odometry's step left out of the graph")
    if spikes:
        said += (f"; scan{'s' if len(spikes) > 1 else ''} {', '.join(map(str, spikes))} had one bad odometry "
                 f"reading (the next scan's step taken from the reading before it)")
    return said


def report(result, source: str = "", notes=()) -> str:
    """The run's settings, counts and time per stage as Markdown; ``notes``, lines about the input
    (a bag's laser mounting), listed first."""
    n = len(result.poses)
    total = sum(result.seconds.values())
    accepted, tried = result.scan_matches
    lines = ["# taichi-match slam", "", f"Input: `{source}`" if source else "", "",
             *(f"- {note}" for note in notes),
             f"- scans: {n}; submaps of {result.options.submap_scans} scans at {result.options.resolution} m",
             f"- scan-to-submap matches accepted: {accepted} of {tried}",
             f"- {loop_summary(result)} (in the graph: accepted, consistent with their neighbours and at the end "
             f"with the optimised graph); matched by helper "
             f"processes: {sum(lp['helper'] for lp in result.loops)}; not matched, already tied (``loop_ties``): "
             f"{result.loops_tied}; not matched, too few walls at the guess: {result.loops_few_walls}",
             f"- odometry steps checked by a search (``jump_check``): "
             f"{sum(c['window'] is not None for c in result.jump_checks)}; "
             f"{jump_summary(result)}",
             f"- final map: {result.map.shape[1]} x {result.map.shape[0]} cells", ""]
    if result.disagreements is not None:
        pairs = result.disagreements
        ending = ":" if pairs else "."
        if pairs and result.options.audit == "repair":
            ending = f"; {sum(p['repaired'] for p in pairs)} of them now joined by a repair closure, optimised again:"
        lines += [f"Audit: {len(pairs)} pairs of submaps disagreed at the poses optimised before the audit (walls of "
                  f"one on the other's free space){ending}", ""]
        notes = {(True, False): "; repaired", (False, True): "; a loop closure in the graph joins them"}
        gated = "; the loop gate took a closure between them out of the graph"
        lines += [f"- submaps {a} and {b}: {p['walls']} walls compared, {p['agreement']:.2f} agree, "
                  f"{p['conflict']:.2f} on free space{notes.get((p['repaired'], p.get('joined', False)), '')}"
                  f"{gated if p.get('gated') else ''}"
                  for p in pairs for a, b in [p["submaps"]]]
        lines += [""] if pairs else []
    lines += ["| stage | seconds | ms per scan |", "|---|---|---|"]
    lines += [f"| {stage} | {sec:.2f} | {1e3 * sec / n:.1f} |" for stage, sec in result.seconds.items()]
    lines += [f"| total | {total:.2f} | {1e3 * total / n:.1f} |", ""]
    if len(result.match_parts):
        target, scan, match = 1e3 * np.median(result.match_parts, axis=0)
        lines += [f"Front-end match, median: {1e3 * np.median(result.match_seconds):.1f} ms (preparing the target "
                  f"{target:.1f} ms, the scan {scan:.1f} ms, matching the prepared maps {match:.1f} ms).", ""]
    if result.add_seconds is not None and len(result.add_seconds) > 2:
        lines += [f"Each scan as it came (``Slam.add``): {scan_times(result)}; a scan that completes a submap "
                  f"waits for its loop closures and an optimisation, {np.mean(result.add_seconds > 0.025):.1%} of "
                  f"the scans over 25 ms.", ""]
    lines += ["Options:", "", "```", repr(result.options), "```", ""]
    return "\n".join(lines)
