"""The ``taichi-match`` command line: parses, calls the library, prints. Heavy imports are lazy."""

import argparse
import dataclasses
import math
import os
import re
import sys
import tempfile

__all__ = ["main"]

MAX_WORKERS = 64          # align-many's worker processes, at most (each starts its own Taichi)


def _demo(args):
    import numpy as np

    import taichi_match as tm
    from taichi_match.scenes import corridor

    grid = corridor()
    r0 = np.array(args.initial, dtype=float)
    matcher = tm.Matcher()
    matcher.match(grid, grid, r0)                        # first call compiles the kernel
    res = matcher.match(grid, grid, r0)
    np.set_printoptions(precision=6, suppress=False)
    print("The paper's corridor: 12 m square map at 0.025 m (480 x 480 cells), 6 m corridor along x;")
    print("B is a copy of A, so the true y and theta are 0 and x is free along the corridor.")
    print(f"initial pose  x={r0[0]:+.4f} m  y={r0[1]:+.4f} m  theta={r0[2]:+.5f} rad")
    x, y, t = res.pose
    print(f"matched pose  x={x:+.4f} m  y={y:+.4f} m  theta={t:+.5f} rad")
    print(f"status        {res.status.name}: {res.message}")
    print(f"iterations    {res.iterations} ({res.launches} kernel launches, {res.evaluations} poses evaluated)")
    print(f"overlap       {res.overlap} cells compared, discrepancy {res.discrepancy:.2f}")
    ev = res.evidence
    print(f"verdict       {'ACCEPTED' if res.accepted else 'NOT ACCEPTED'}: {ev.walls_compared} walls compared, "
          f"{100 * ev.wall_agreement:.0f} % meet walls, {100 * ev.wall_conflict:.0f} % on free space")
    print("calibrated covariance (x, y, theta):")
    print(res.calibrated_covariance)
    for d in res.degenerate:
        dx, dy, dt = np.round(d, 4) + 0.0
        print(f"degenerate direction (no information): ({dx:+.4f}, {dy:+.4f}, {dt:+.4f}) in (x, y, theta)")
    print(f"time          {1e3 * res.seconds:.1f} ms (the paper: about 6 s)")
    if args.plot:
        try:
            from taichi_match import plots
            plots.save_overlay(args.plot, grid, grid, r0, res, title="taichi-match demo: the paper's corridor")
            print(f"picture       {args.plot}")
        except ImportError as exc:
            print(f"picture       not written: {exc}")
    return EXIT_OK if res.accepted else EXIT_NOT_ACCEPTED


def _reproduce(args):
    from taichi_match.reproduce import reproduce

    bar = _progress("matching", None, args.progress or sys.stderr.isatty(), unit="match")
    out = reproduce(args.out, trials=args.trials, covariance_trials=args.covariance_trials, seed=args.seed,
                    progress=bar)
    print(open(os.path.join(args.out, "report.md")).read().split("## Figures")[0].rstrip())
    print(f"\nwrote {os.path.join(args.out, 'report.md')}, results.json, config.json and "
          f"{len(out['results']['figures'])} figures in {out['results']['seconds']:.0f} s")
    return EXIT_OK


EXIT_OK, EXIT_NOT_ACCEPTED, EXIT_BAD_INPUT = 0, 1, 2
EXIT_INTERRUPTED, EXIT_BROKEN_PIPE = 130, 141            # 128 + SIGINT, 128 + SIGPIPE, as a shell reports them


def _map_overrides(args, which):
    thresholds = getattr(args, f"thresholds_{which}")
    resolution = getattr(args, f"resolution_{which}")
    out = {}
    if thresholds is not None:
        out["occupied_thresh"], out["free_thresh"] = thresholds
    if resolution is not None:
        out["resolution"] = resolution
    return out


def _load_pair(args):
    from taichi_match.io import load_map

    return load_map(args.map_a, **_map_overrides(args, "a")), load_map(args.map_b, **_map_overrides(args, "b"))


def _align(args):
    import json

    import numpy as np

    import taichi_match as tm

    a, b = _load_pair(args)
    if args.window is not None and args.initial is None:
        raise tm.InvalidOptionError("--window needs --initial: the guess to search around")
    window = None if args.window is None else (args.window[0], np.radians(args.window[1]))
    res = tm.Matcher(_match_options(args)).match(a, b, args.initial, search_window=window)
    cov = res.calibrated_covariance
    edge = None                             # the g2o EDGE_SE2 line: pose and information matrix
    if args.g2o is not None and not res.accepted:
        print("taichi-match: the match is not accepted: no g2o edge written", file=sys.stderr)
    elif args.g2o is not None:
        info = np.linalg.inv(cov)
        edge = (f"EDGE_SE2 {args.g2o[0]} {args.g2o[1]} {res.pose[0]:.6f} {res.pose[1]:.6f} {res.pose[2]:.6f} "
                + " ".join(f"{info[i, j]:.6g}" for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))))
    if args.json:                           # stdout is one JSON document, the edge inside it
        print(json.dumps({**_result_dict(res), "g2o": edge}, indent=2))
    else:
        x, y, t = res.pose
        print(f"pose (B in A)  x={x:+.4f} m  y={y:+.4f} m  theta={t:+.5f} rad")
        print(f"status         {res.status.name}: {res.message}")
        ev = res.evidence
        print(f"verdict        {'ACCEPTED' if res.accepted else 'NOT ACCEPTED'}: {ev.walls_compared} walls compared, "
              f"{100 * ev.wall_agreement:.0f} % meet the other map's walls, {100 * ev.wall_conflict:.0f} % land on "
              f"its free space, uncertainty {100 * ev.uncertainty:.1f} cm")
        if not res.accepted:
            print(f"not accepted   {_refusal(res)}")
        print(f"iterations     {res.iterations}, overlap {res.overlap} cells, time {1e3 * res.seconds:.1f} ms")
        for k, h in enumerate(res.hypotheses):
            hx, hy, ht = h.pose
            print(f"{'searched' if k == 0 else 'runner-up':14} x={hx:+.4f} m  y={hy:+.4f} m  theta={ht:+.5f} rad  "
                  f"score {h.score:.1f}" + (f" ({h.score / res.hypotheses[0].score:.2f} of the best)"
                                            if k and res.hypotheses[0].score > 0 else ""))
        print("covariance (x, y, theta), calibrated:")
        print(np.array2string(cov, precision=6))
        for d in res.degenerate:
            print("degenerate direction:", np.round(d, 4) + 0.0)
        if edge is not None:
            print(edge)
    if args.plot:
        from taichi_match import plots
        plots.save_overlay(args.plot, a, b, res.initial_pose, res, title=f"{args.map_a} + {args.map_b}")
    return EXIT_OK if res.accepted else EXIT_NOT_ACCEPTED


def _read_pairs(path, degrees):
    """The pairs of a CSV file: rows ``A, B`` or ``A, B, X, Y, THETA`` (a guess of B's pose in A,
    THETA in radians or ``degrees``); map paths relative to the file's folder; blank lines, lines
    starting with # and a first row starting with ``map_a`` (a header) are skipped. Returns
    [(row number, path A, path B, guess or None)]."""
    import csv

    from taichi_match import InvalidOptionError, MapFileError

    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as exc:
        raise MapFileError(f"cannot read the pairs file {path!r}: {exc}") from exc
    folder = os.path.dirname(os.path.abspath(path))
    pairs = []
    for number, row in enumerate(rows, 1):
        row = [field.strip() for field in row]
        if not any(row) or row[0].startswith("#") or (number == 1 and row[0].lower() == "map_a"):
            continue
        if len(row) not in (2, 5) or not row[0] or not row[1]:
            raise InvalidOptionError(f"{path}:{number}: a row is A, B or A, B, X, Y, THETA; got {len(row)} fields")
        guess = None
        if len(row) == 5:
            try:
                guess = [float(v) for v in row[2:]]
            except ValueError:
                raise InvalidOptionError(f"{path}:{number}: X, Y, THETA must be numbers; got {row[2:]}") from None
            if degrees:
                guess[2] = math.radians(guess[2])
        pairs.append((number, *(os.path.join(folder, os.path.expanduser(p)) for p in row[:2]), guess))
    if not pairs:
        raise InvalidOptionError(f"{path}: no pairs (rows A, B or A, B, X, Y, THETA)")
    return pairs


def _with_images(paths):
    """The map files ``paths`` and the images that the readable ROS map YAMLs among them name: what
    an output must never overwrite (an unreadable map is reported where it is read)."""
    from taichi_match import TaichiMatchError
    from taichi_match.io import read_map_yaml

    out = list(paths)
    for path in paths:
        if str(path).lower().endswith((".yaml", ".yml")):
            try:
                out.append(read_map_yaml(path)["image"])
            except (TaichiMatchError, OSError, ValueError):
                pass
    return out


def _align_many(args):
    import json
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    import taichi_match as tm
    from taichi_match.io import load_map

    options = _match_options(args)
    if not 1 <= args.workers <= MAX_WORKERS:
        raise tm.InvalidOptionError(f"--workers must be 1 to {MAX_WORKERS}; got {args.workers}")
    pairs = _read_pairs(args.pairs, args.degrees)
    out = sys.stdout if args.output in (None, "-") else None
    if out is None:
        if os.path.exists(args.output):
            inputs = [args.pairs] + _with_images({path for pair in pairs for path in pair[1:3]})
            if any(os.path.exists(p) and os.path.samefile(p, args.output) for p in inputs):
                raise tm.MapFileError(f"refusing to write {args.output!r}: it is an input")
            if not args.force:
                raise tm.MapFileError(f"{args.output!r} exists: use --force to replace it")
    maps, failed = {}, {}                       # each map read once, however many pairs name it
    for _, *paths, _ in pairs:
        for p in paths:
            if p not in maps and p not in failed:
                try:
                    maps[p] = load_map(p)
                except (tm.TaichiMatchError, ValueError, OSError) as exc:
                    failed[p] = str(exc)
    runnable = [(k, pair) for k, pair in enumerate(pairs) if pair[1] in maps and pair[2] in maps]
    tasks = [(maps[a], maps[b], guess) for _, (_, a, b, guess) in runnable]
    lines, written, accepted = {}, 0, 0
    for k, (_number, a, b, _) in enumerate(pairs):
        if a in failed or b in failed:
            lines[k] = {"error": failed.get(a) or failed.get(b)}
    bar = _progress("align-many", len(pairs), args.progress or sys.stderr.isatty(), unit="pair")
    executor = (ProcessPoolExecutor(args.workers, mp_context=multiprocessing.get_context("spawn"))
                if args.workers > 1 else None)
    # an output that exists (--force) is replaced only once every line is written: an interrupted
    # run leaves it as it was (a new one is written as the results come)
    replacing = out is None and os.path.exists(args.output)
    temporary, done = None, False
    if replacing:
        folder, name = os.path.split(os.path.abspath(args.output))
        handle, temporary = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=folder)
        stream = os.fdopen(handle, "w")
    else:
        stream = out or open(args.output, "w")
    try:
        results = tm.iter_matches(tasks, options, executor=executor, chunk_size=args.chunk_size, errors="return")
        while True:
            while written in lines:             # in the file's order, each line as soon as it can be
                number, a, b, _ = pairs[written]
                record = {"row": number, "map_a": a, "map_b": b, **lines.pop(written)}
                accepted += bool(record.get("accepted"))
                stream.write(json.dumps(record) + "\n")
                stream.flush()
                written += 1
                if bar is not None:
                    bar(written, len(pairs))
            if written == len(pairs):
                break
            index, res = next(results)
            k = runnable[index][0]
            lines[k] = {"error": str(res)} if isinstance(res, Exception) else _result_dict(res)
        done = True
    finally:
        if executor is not None:
            executor.shutdown(cancel_futures=True)
        if out is None:
            stream.close()
        if temporary is not None:
            if done:
                os.replace(temporary, args.output)
            else:
                os.unlink(temporary)
    if out is None:
        print(f"{accepted} of {len(pairs)} pairs accepted; wrote {args.output}", file=sys.stderr)
    return EXIT_OK if accepted == len(pairs) else EXIT_NOT_ACCEPTED


def _match_options(args):
    """The MatchOptions the command's options ask for: the paper's settings (MatchOptions.paper)
    under the paper's discrepancy, the defaults otherwise, with the options given on top."""
    import taichi_match as tm

    options = {k: v for k, v in (("blur", args.blur), ("blur_kind", args.blur_kind),
                                 ("prior_weight", args.prior_weight),
                                 ("rotation_scale", args.rotation_scale), ("max_iterations", args.max_iterations),
                                 ("interpolation", args.interpolation), ("optimizer", args.optimizer))
               if v is not None}
    base = tm.MatchOptions.paper() if args.blur_kind in ("gaussian", "ramp") else tm.MatchOptions()
    return dataclasses.replace(base, **options) if options else base


def _result_dict(res) -> dict:
    """A MatchResult as plain JSON types (the calibrated covariance as "covariance")."""
    import numpy as np

    return {
        "pose": res.pose.tolist(), "covariance": res.calibrated_covariance.tolist(),
        "covariance_unscaled": res.covariance.tolist(),
        "information": res.information.tolist(), "degenerate": res.degenerate.tolist(),
        "accepted": bool(res.accepted), "evidence": {
            "walls_compared": res.evidence.walls_compared, "wall_agreement": res.evidence.wall_agreement,
            "wall_conflict": res.evidence.wall_conflict,
            "uncertainty_m": res.evidence.uncertainty if np.isfinite(res.evidence.uncertainty) else None},
        "status": res.status.name, "converged": bool(res.converged), "message": res.message,
        "iterations": res.iterations, "launches": res.launches, "seconds": res.seconds,
        "overlap": res.overlap, "discrepancy": res.discrepancy, "initial_pose": res.initial_pose.tolist(),
        "hypotheses": [{"pose": h.pose.tolist(), "score": h.score} for h in res.hypotheses],
        "search_complete": res.search_complete, "search_proven": res.search_proven,
        "not_accepted_because": _refusal(res) or None,
    }


def _refusal(res) -> str:
    """Why ``res`` is not accepted, in a few words each reason (empty when it is)."""
    if res.accepted:
        return ""
    from taichi_match._matcher import AMBIGUITY
    from taichi_match._verdict import MAX_CONFLICT, MAX_UNCERTAINTY_M, MIN_AGREEMENT, MIN_WALLS

    ev, hyp = res.evidence, res.hypotheses
    reasons = [] if res.converged else [f"not converged ({res.status.name})"]
    if res.search_complete is False:
        reasons.append("the search stopped at its node budget, the best pose not proven")
    if hyp and hyp[0].score <= 0:
        reasons.append(f"the best searched pose scores {hyp[0].score:.0f}: B disagrees with A more than it agrees")
    elif len(hyp) > 1 and hyp[1].score >= AMBIGUITY * hyp[0].score:
        reasons.append(f"ambiguous: a runner-up scores {hyp[1].score / hyp[0].score:.2f} of the best")
    compared = ev.walls_compared > 0          # with none, the shares are placeholders (0 and 1), not findings
    for bad, what in ((ev.walls_compared < MIN_WALLS, f"{ev.walls_compared} walls compared (< {MIN_WALLS})"),
                      (compared and ev.wall_agreement < MIN_AGREEMENT, f"{100 * ev.wall_agreement:.0f} % of walls "
                                                                       f"agree (< {100 * MIN_AGREEMENT:.0f})"),
                      (compared and ev.wall_conflict > MAX_CONFLICT, f"{100 * ev.wall_conflict:.0f} % of walls on "
                                                                     f"free space (> {100 * MAX_CONFLICT:.0f})"),
                      (not ev.uncertainty <= MAX_UNCERTAINTY_M, f"uncertainty {100 * ev.uncertainty:.1f} cm "
                                                                f"(> {100 * MAX_UNCERTAINTY_M:.0f})")):
        if bad:
            reasons.append(what)
    return "; ".join(reasons)


def _merge(args):
    from taichi_match import MapFileError
    from taichi_match.io import ros_map_paths, write_ros_map
    from taichi_match.merge import merge_maps

    output, image = ros_map_paths(args.output, args.mode)
    inputs = _with_images([args.map_a, args.map_b])
    for target in (output, image):
        if os.path.exists(target):
            clash = [path for path in inputs if os.path.exists(path) and os.path.samefile(path, target)]
            if clash:
                raise MapFileError(f"refusing to write {target!r}: it is the input {clash[0]!r}")
            if not args.force:
                raise MapFileError(f"{target!r} exists: use --force to replace it")
    a, b = _load_pair(args)
    pose = args.pose
    if pose is None:                        # align first, without a guess
        import taichi_match as tm

        res = tm.match(a, b)
        if not res.accepted:
            print(f"taichi-match: the search's alignment is not accepted ({_refusal(res)}): nothing written; "
                  f"give --pose", file=sys.stderr)
            return EXIT_NOT_ACCEPTED
        pose = res.pose
        print(f"aligned: x={pose[0]:+.4f} m  y={pose[1]:+.4f} m  theta={pose[2]:+.5f} rad")
    merged = merge_maps(a, b, pose, fusion=args.fusion)
    write_ros_map(merged, output, mode=args.mode)
    print(f"wrote {args.output}: {merged.shape[0]} x {merged.shape[1]} cells at {merged.resolution} m, "
          f"origin {merged.origin}")
    if args.plot:
        from taichi_match import plots

        plots.save_merge(args.plot, a, b, merged, title=f"{args.map_a} + {args.map_b}")
        print(f"picture {args.plot}")
    return EXIT_OK


def _slam(args):
    import numpy as np

    from taichi_match import InvalidOptionError
    from taichi_match.logs import read_carmen, read_tum
    from taichi_match.slam import Slam, SlamOptions, jump_summary, loop_summary, output_paths, scan_times, write_outputs

    output_paths(args.out, force=args.force, keep=(args.log, args.reference))      # before any work
    bag = os.path.isdir(args.log) or os.path.splitext(args.log)[1] in (".bag", ".db3", ".mcap")
    if bag and args.max_range is not None:
        raise InvalidOptionError("--max-range applies to CARMEN logs only (a bag's LaserScan gives its own "
                                 "range_max)")
    for flag, given in (("--scan-topic", args.scan_topic), ("--odom-topic", args.odom_topic),
                        ("--laser-pose", args.laser_pose), ("--laser-upside-down", args.laser_upside_down or None)):
        if not bag and given is not None:
            raise InvalidOptionError(f"{flag} applies to ROS bags only ({args.log} is read as a CARMEN log, whose "
                                     f"scans carry the laser's pose)")
    if bag:
        import warnings

        from taichi_match.bags import LaserMountWarning, read_rosbag

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", LaserMountWarning)
            try:
                log, left_out = read_rosbag(args.log, scan_topic=args.scan_topic, odometry_topic=args.odom_topic,
                                            laser_pose=args.laser_pose, upside_down=args.laser_upside_down)
            except InvalidOptionError as exc:         # name the flags the user typed
                text = str(exc).replace("laser_pose", "--laser-pose").replace("upside_down", "--laser-upside-down")
                raise InvalidOptionError(text) from None
        for warning in caught:                        # ours as a line; any other as Python shows it
            if issubclass(warning.category, LaserMountWarning):
                print(f"taichi-match: warning: {warning.message}", file=sys.stderr)
            else:
                warnings.showwarning(warning.message, warning.category, warning.filename, warning.lineno)
        if left_out:
            print(f"{left_out} scans outside the odometry's time span left out")
    else:
        log = read_carmen(args.log, max_range=args.max_range)
    reference = None
    if args.reference:
        stamps, reference = read_tum(args.reference)
        if len(stamps) != len(log) or not np.allclose(stamps, log.timestamps, rtol=0.0, atol=1e-3):
            raise ValueError(f"{args.reference}: the reference must hold one pose per scan, at the scans' "
                             f"timestamps ({len(stamps)} poses for {len(log)} scans)")
    off = {"off": None}
    given = {"submap_scans": ("--submap-scans", args.submap_scans), "resolution": ("--resolution", args.resolution),
             "max_ray_length": ("--max-ray", args.max_ray), "free_margin": ("--free-margin", args.free_margin),
             "target_refresh": ("--target-refresh", args.target_refresh),
             "submap_frames": ("--submap-frames", args.submap_frames),
             "share_coarse": ("--share-coarse", args.share_coarse or None),
             "crop_target": ("--crop-target", args.crop_target or None),
             "loop_radius": ("--loop-radius", args.loop_radius), "loop_search": ("--loop-search", args.loop_search),
             "workers": ("--workers", args.workers), "loop_ties": ("--loop-ties", args.loop_ties),
             "solver": ("--solver", args.solver), "audit": ("--audit", args.audit),
             "front_end_inflation": ("--front-end-inflation", args.front_end_inflation),
             "gate_inflation": ("--gate-inflation", args.gate_inflation), "loop_gate": ("--loop-gate", args.loop_gate),
             "odometry_sd": ("--odometry-sd", None if args.odometry_sd is None else tuple(args.odometry_sd)),
             "loop_growth": ("--loop-growth", args.loop_growth),
             "robust_kernel": ("--robust-kernel", args.robust_kernel),
             "loop_consistency": ("--loop-consistency", args.loop_consistency),
             "jump_check": ("--jump-check", args.jump_check), "turn_edge": ("--turn-edge", args.turn_edge)}
    try:
        options = SlamOptions(**{field: off.get(value, value) if isinstance(value, str) else value
                                 for field, (_, value) in given.items() if value is not None})
    except InvalidOptionError as exc:                 # name the flag the user typed, not the field
        field = str(exc).split(" ", 1)[0]
        raise InvalidOptionError(f"{given[field][0]}: {exc}" if field in given else str(exc)) from None
    front_end = {k: v for k, v in (("levels", args.front_end_levels), ("interpolation", args.front_end_lookup))
                 if v is not None}
    if front_end:
        options = dataclasses.replace(options, scan_matcher=options.scan_matcher.replace(**front_end))
    if args.loop_grid_edge is not None:
        options = dataclasses.replace(options, matcher=options.matcher.replace(grid_edge=args.loop_grid_edge))
    bar = _progress(f"slam {os.path.basename(args.log)}", len(log), args.progress or sys.stderr.isatty())
    result = Slam(options).run(log, progress=bar)
    notes = [f"the laser on the robot: {log.laser_mount}"] if log.laser_mount else []
    paths = write_outputs(result, args.out, source=args.log, force=args.force, keep=(args.log, args.reference),
                          notes=notes)
    accepted, tried = result.scan_matches
    seconds = sum(result.seconds.values())
    print(f"{len(log)} scans in {seconds:.1f} s ({1e3 * seconds / len(log):.1f} ms per scan); scan matches accepted "
          f"{accepted}/{tried}; {loop_summary(result)}{_audit_line(result)}")
    print(f"each scan as it came: {scan_times(result)}")
    if any(check["jump"] for check in result.jump_checks):
        print(f"{jump_summary(result)} (report.md)")
    if reference is not None:
        from taichi_match.evaluation import trajectory_errors

        errors = trajectory_errors(result.poses, reference)
        odometry = trajectory_errors(log.poses, reference)
        print(f"ATE {errors['ate_m']:.3f} m {errors['ate_deg']:.2f} deg (odometry {odometry['ate_m']:.3f} m "
              f"{odometry['ate_deg']:.2f} deg); RPE over 10 scans {errors['rpe_m']:.3f} m {errors['rpe_deg']:.2f} deg "
              f"(odometry {odometry['rpe_m']:.3f} m {odometry['rpe_deg']:.2f} deg)")
    for name in ("trajectory", "map", "image", "graph", "report"):
        print(f"{name:10s} {paths[name]}")
    if accepted == 0 or accepted < tried / 4:          # (the shared logs: 80-99 % accepted)
        what = ("no scan match was accepted: the trajectory is the odometry's" if accepted == 0 else
                f"only {accepted} of {tried} scan matches were accepted: the trajectory is mostly the odometry's")
        print(f"taichi-match: {what} (see report.md; --resolution and --max-ray set what a scan can show; scans "
              f"that do not overlap their predecessors, as from a wrong beam order, match nothing)", file=sys.stderr)
        return EXIT_NOT_ACCEPTED
    return EXIT_OK


def _demo_slam(args):
    from taichi_match.evaluation import align_se2, trajectory_errors
    from taichi_match.simulate import simulate_log
    from taichi_match.slam import Slam, loop_summary, scan_times

    run = simulate_log(args.seed)
    print(f"A simulated robot twice round a 24 x 16 m floor plan (taichi_match.simulate, seed {args.seed}): "
          f"{len(run.log)} scans of 181 beams, 0.5 m apart, odometry drifting by 1 % and 0.15 deg per metre.")
    bar = _progress("slam", len(run.log), args.progress or sys.stderr.isatty())
    result = Slam().run(run.log, progress=bar)
    errors = trajectory_errors(result.poses, run.truth)
    odometry = trajectory_errors(run.log.poses, run.truth)
    accepted, tried = result.scan_matches
    seconds = sum(result.seconds.values())
    print(f"scan-to-submap matches accepted {accepted}/{tried}; {loop_summary(result)}{_audit_line(result)}")
    print(f"against the simulated truth: ATE {errors['ate_m']:.3f} m {errors['ate_deg']:.2f} deg, RPE over 10 scans "
          f"{errors['rpe_m']:.3f} m {errors['rpe_deg']:.2f} deg")
    print(f"the odometry alone:          ATE {odometry['ate_m']:.3f} m {odometry['ate_deg']:.2f} deg, "
          f"RPE over 10 scans {odometry['rpe_m']:.3f} m {odometry['rpe_deg']:.2f} deg")
    print(f"time {seconds:.1f} s, {1e3 * seconds / len(run.log):.0f} ms per scan; each scan as it came: "
          f"{scan_times(result)}")
    if args.plot:
        try:
            from taichi_match import plots
            plots.save_trajectories(args.plot, result.map, {                    # in the map's frame
                "odometry": (align_se2(run.log.poses, result.poses), "tab:orange", "-"),
                "truth": (align_se2(run.truth, result.poses), "tab:green", "-"),
                "taichi-match slam": (result.poses, "tab:red", "--")},
                title="taichi-match demo-slam: the simulated run")
            print(f"picture {args.plot}")
        except ImportError as exc:
            print(f"picture not written: {exc}")
    return EXIT_OK


def _metres_or_off(text: str):
    """A number of metres, or "off"."""
    return _number_or_off(text, "a number of metres")


def _number_or_off(text: str, what: str = "a number"):
    """A number, or "off"."""
    if text.strip().lower() == "off":
        return "off"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what} or 'off', got {text!r}") from None


def _audit_line(result) -> str:
    """The audit's finding in a line, for the summaries ("" without ``audit``)."""
    pairs = result.disagreements
    if pairs is None:
        return ""
    line = f"\nthe audit (the map's self-check): {len(pairs)} pairs of submaps disagreed"
    if pairs and result.options.audit == "repair":
        line += f", {sum(p['repaired'] for p in pairs)} of them joined by a repair closure since"
    return line


def _progress(label, total, enabled, unit="scan"):
    """A tqdm bar on stderr, ``bar(done, total)``; None when not ``enabled`` or without tqdm (the
    ``slam`` extra): the work runs the same without one."""
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    try:
        bar = tqdm(total=total, desc=label, unit=unit, file=sys.stderr)
    except OSError:                      # stderr closed already
        return None
    broken = []

    def update(done, _total):
        if broken:
            return
        try:
            bar.total = _total
            bar.update(done - bar.n)
            if done >= _total:
                bar.close()
        except OSError:                  # stderr closed (a pipe whose reader left): the work goes on without it
            broken.append(True)
    return update


def _add_map_arguments(parser):
    parser.add_argument("map_a", metavar="A.yaml", help="map A (map_server .yaml or .npz)")
    parser.add_argument("map_b", metavar="B.yaml", help="map B")
    for which in ("a", "b"):
        parser.add_argument(f"--thresholds-{which}", nargs=2, type=float, metavar=("OCC", "FREE"),
                            help=f"override map {which.upper()}'s occupied_thresh and free_thresh")
        parser.add_argument(f"--resolution-{which}", type=float, metavar="M",
                            help=f"override map {which.upper()}'s resolution (metres per cell)")


def _add_match_options(parser):
    """The match options of align and align-many (``_match_options`` reads them)."""
    parser.add_argument("--blur", type=float, help="blur width, metres")
    parser.add_argument("--blur-kind", choices=("envelope", "gaussian", "ramp"),
                        help="the discrepancy: 'envelope' (default) or the paper's |p_A - p_B| on a 'gaussian' "
                             "or 'ramp' blur")
    parser.add_argument("--interpolation", choices=("nearest", "bilinear"),
                        help="lookup: nearest cell (the paper's, default) or bilinear (each lookup "
                             "interpolated between the four cell centres around it: slower, smooth)")
    parser.add_argument("--optimizer", choices=("newton", "bfgs"),
                        help="default: bfgs for the paper's discrepancy with bilinear, else newton")
    parser.add_argument("--prior-weight", type=float, help="K of eq. (8)")
    parser.add_argument("--rotation-scale", type=float, help="L of eq. (7), metres per radian")
    parser.add_argument("--max-iterations", type=int, help="optimiser iterations at the coarsest level (0: none)")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("taichi-match")
    except PackageNotFoundError:                 # run from a source tree that was never installed
        return "unknown (not installed)"


def _check_picture(args):
    """--plot checked before any work (bad input, exit 2): matplotlib there, a .png, .pdf or .svg
    file in an existing folder, and never one of the input maps or their images."""
    import importlib.util

    from taichi_match import InvalidOptionError
    from taichi_match.plots import check_picture_path

    if importlib.util.find_spec("matplotlib") is None:
        raise InvalidOptionError("--plot needs matplotlib: pip install 'taichi-match[plots]'")
    check_picture_path(args.plot)
    inputs = _with_images([args.map_a, args.map_b])
    if os.path.exists(args.plot) and any(os.path.exists(p) and os.path.samefile(p, args.plot) for p in inputs):
        raise InvalidOptionError(f"refusing to write the picture over {args.plot!r}: it is an input")


class _Parser(argparse.ArgumentParser):
    """argparse, with its errors on one line like every other error of the command, and values
    such as -1e-3 or -.5 read as numbers (argparse before Python 3.13 took them for options)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-\.?\d")          # Python 3.13's pattern

    def error(self, message):
        self.exit(EXIT_BAD_INPUT, f"taichi-match: error: {message} (see {self.prog} --help)\n")


def main(argv=None):
    parser = _Parser(
        prog="taichi-match", description="Relative pose between overlapping occupancy grid maps.")
    parser.add_argument("--version", action="version", version=f"taichi-match {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="match the paper's corridor against a copy of itself")
    demo.add_argument("--initial", nargs=3, type=float, metavar=("X", "Y", "THETA"), default=(0.8, -1.1, 0.3),
                      help="initial guess of B's pose in A (metres, metres, radians)")
    demo.add_argument("--plot", default="taichi_match_demo.png", metavar="PNG",
                      help="where to write the overlay picture (default: %(default)s; '' for none)")
    demo.set_defaults(func=_demo)
    rep = sub.add_parser("reproduce", help="regenerate the paper's tables and figures and the covariance check")
    rep.add_argument("--out", required=True, metavar="DIR", help="output folder")
    rep.add_argument("--trials", type=int, default=100, help="trials per table row (default: %(default)s)")
    rep.add_argument("--covariance-trials", type=int, default=300,
                     help="matches per noise level of the covariance check (default: %(default)s)")
    rep.add_argument("--seed", type=int, default=0, help="seed of the initial poses and noise (default: %(default)s)")
    rep.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    rep.set_defaults(func=_reproduce)
    align = sub.add_parser("align", help="find the pose of map B in map A (exit 0: accepted, 1: not accepted, "
                                         "2: bad input)")
    _add_map_arguments(align)
    align.add_argument("--initial", nargs=3, type=float, metavar=("X", "Y", "THETA"),
                       help="initial guess of B's pose in A (metres, metres, radians); without it a search over "
                            "every pose where the maps overlap finds one")
    align.add_argument("--degrees", action="store_true", help="THETA of --initial is in degrees, not radians")
    align.add_argument("--window", nargs=2, type=float, metavar=("METRES", "DEGREES"),
                       help="search within this window around --initial first (a guess beyond the local "
                            "matcher's basin)")
    align.add_argument("--json", action="store_true", help="print the result as JSON")
    align.add_argument("--plot", metavar="PNG", help="write the overlay of the aligned maps with the covariance")
    align.add_argument("--g2o", nargs=2, type=int, metavar=("ID_A", "ID_B"),
                       help="also print a g2o EDGE_SE2 line (pose and information matrix; with --json, the "
                            "document's \"g2o\" field)")
    _add_match_options(align)
    align.set_defaults(func=_align)
    many = sub.add_parser("align-many", help="align the pairs of a CSV file (rows A, B or A, B, X, Y, THETA), one "
                                             "JSON line per pair in the file's order (exit 0: every pair accepted, "
                                             "1: not every pair, 2: bad input)")
    many.add_argument("pairs", metavar="PAIRS.csv", help="rows: map A, map B (map_server .yaml or .npz, relative to "
                                                         "the file's folder), optionally a guess X, Y, THETA of B's "
                                                         "pose in A (metres, radians); without one, a search")
    many.add_argument("--degrees", action="store_true", help="THETA of the guesses is in degrees, not radians")
    many.add_argument("-o", "--output", metavar="OUT.jsonl", help="write the JSON lines here (default: stdout)")
    many.add_argument("--force", action="store_true", help="replace an existing --output (never an input)")
    many.add_argument("--workers", type=int, default=1,
                      help="worker processes (default %(default)s: this process); each map is read once and sent "
                           "to a worker with the pairs that name it")
    many.add_argument("--chunk-size", type=int, metavar="N",
                      help="pairs per chunk sent to a worker (default: the pairs shared evenly)")
    many.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    _add_match_options(many)
    many.set_defaults(func=_align_many)
    merge = sub.add_parser("merge", help="fuse map B into map A's frame and save a map_server map")
    _add_map_arguments(merge)
    merge.add_argument("--pose", nargs=3, type=float, metavar=("X", "Y", "THETA"),
                       help="B's pose in A (from align); without it the maps are aligned first by a search "
                            "(nothing is written unless that alignment is accepted)")
    merge.add_argument("--degrees", action="store_true", help="THETA of --pose is in degrees, not radians")
    merge.add_argument("-o", "--output", required=True, metavar="MERGED.yaml",
                       help="the merged map's YAML; its image goes beside it as MERGED.pgm (.png in scale mode)")
    merge.add_argument("--force", action="store_true", help="replace an existing output (never an input)")
    merge.add_argument("--mode", choices=("trinary", "scale", "raw"), default="trinary",
                       help="how the image encodes the map (map_server's modes; default: %(default)s)")
    # merge.FUSIONS written out: --help imports nothing heavy
    merge.add_argument("--fusion", choices=("max", "log-odds"), default="max",
                       help="where both maps know a cell: the larger probability, so an obstacle either map "
                            "saw stays one (default), or the evidence added in log-odds")
    merge.add_argument("--plot", metavar="PNG", help="also write A, B and the merged map side by side (.png, .pdf "
                                                      "or .svg; needs matplotlib)")
    merge.set_defaults(func=_merge)
    demo_slam = sub.add_parser("demo-slam", help="the mapping loop on a simulated robot, against its exact truth "
                                                 "(needs gtsam: pip install 'taichi-match[slam]')")
    demo_slam.add_argument("--seed", type=int, default=0, help="the floor plan's and the noise's seed")
    demo_slam.add_argument("--plot", default="taichi_match_slam_demo.png", metavar="PNG",
                           help="where to write the picture (default: %(default)s; '' for none)")
    demo_slam.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    demo_slam.set_defaults(func=_demo_slam)
    slam = sub.add_parser("slam", help="map a laser log: corrected trajectory, map, pose graph and report "
                                       "(needs gtsam: pip install 'taichi-match[slam]'; exit 0: done, 1: fewer "
                                       "than a quarter of the scan matches accepted, the trajectory mostly the "
                                       "odometry's, 2: bad input)")
    slam.add_argument("log", help="CARMEN log (.log, .clf, gzipped or not), or a ROS 1 (.bag) or ROS 2 bag "
                                   "(folder, .db3, .mcap) with sensor_msgs/LaserScan and nav_msgs/Odometry")
    slam.add_argument("--scan-topic", help="the LaserScan topic of a bag that has several")
    slam.add_argument("--odom-topic", help="the Odometry topic of a bag that has several")
    slam.add_argument("--laser-pose", type=float, nargs=3, metavar=("X", "Y", "THETA"),
                      help="a bag's laser pose on the robot: metres and radians in the odometry's child frame, "
                           "level (default: from the bag's /tf_static; without it the laser sits at the base)")
    slam.add_argument("--laser-upside-down", action="store_true",
                      help="with --laser-pose: the laser is mounted upside down (its beams' angles negated)")
    slam.add_argument("--out", required=True, metavar="DIR", help="output folder (created if missing)")
    slam.add_argument("--force", action="store_true", help="replace existing outputs in DIR")
    slam.add_argument("--reference", metavar="TUM", help="a reference trajectory: print ATE and RPE against it")
    slam.add_argument("--submap-scans", type=int, metavar="N", help="scans per submap (even, default 10)")
    slam.add_argument("--target-refresh", type=int, metavar="N", help="the front end casts its target submap again "
                                                                      "after N scans (default 1: for every scan)")
    slam.add_argument("--loop-radius", type=float, metavar="METRES",
                      help="loop-closure candidates: submaps whose frames lie within this many metres plus a tenth "
                           "of the travel between them (default 3, see SlamOptions.loop_radius)")
    slam.add_argument("--loop-search", type=float, metavar="METRES",
                      help="search loop-closure candidates whose drift bound exceeds this within a window first "
                           "(see SlamOptions.loop_search)")
    slam.add_argument("--audit", choices=("off", "report", "repair"),
                      help="after the last optimisation, list the submaps that disagree at their poses (walls of "
                           "one on the other's free space) in report.md; 'repair' (the default) also searches a "
                           "loop closure between each such pair and optimises again; 'off': no check (see "
                           "SlamOptions.audit)")
    slam.add_argument("--loop-ties", type=_metres_or_off, metavar="METRES",
                      help="skip loop-closure candidates that closures already in the graph tie within this many "
                           "metres of travel, or 'off' (see SlamOptions.loop_ties)")
    slam.add_argument("--solver", choices=("batch", "isam2"),
                      help="the pose graph's optimisation after each submap: batch Levenberg-Marquardt (default) or "
                           "incremental iSAM2, for long runs (see SlamOptions.solver)")
    slam.add_argument("--submap-frames", action=argparse.BooleanOptionalAction,
                      help="give each submap its own node in the pose graph (default), or tie it to its first "
                           "scan's node (see SlamOptions.submap_frames)")
    slam.add_argument("--share-coarse", action="store_true",
                      help="prepare only the finest level of the front end's target for each scan, its coarser "
                           "levels once per target (see SlamOptions.share_coarse)")
    slam.add_argument("--crop-target", action="store_true",
                      help="cast the front end's target only around where each scan can land "
                           "(see SlamOptions.crop_target)")
    slam.add_argument("--workers", type=int, metavar="N",
                      help="helper processes matching loop-closure candidates beside this one (the same results; "
                           "default 0, see SlamOptions.workers)")
    slam.add_argument("--front-end-inflation", type=float, metavar="X",
                      help="the front end's scan-to-submap edges enter the graph with X times their match "
                           "covariance (default 6, see SlamOptions.front_end_inflation)")
    slam.add_argument("--gate-inflation", type=float, metavar="X",
                      help="the odometry gate takes X times a front-end match's covariance (default 2, see "
                           "SlamOptions.gate_inflation)")
    slam.add_argument("--loop-gate", type=_number_or_off, metavar="CHI2",
                      help="at the end, take out of the graph the loop closures whose residual at the optimised "
                           "poses exceeds this chi-square in their own covariance, and optimise again (default "
                           "16.27, 99.9 %% with 3 degrees of freedom), or 'off' (see SlamOptions.loop_gate)")
    slam.add_argument("--odometry-sd", type=float, nargs=5,
                      metavar=("PER_M", "PER_RAD", "RAD_PER_M", "FLOOR_M", "FLOOR_RAD"),
                      help="your robot's odometry model, the standard deviations of a step: metres per metre "
                           "travelled, radians per radian turned, radians per metre, and the metres and radians "
                           "floors (default 0.02 0.02 0.0052 0.005 0.0017, see SlamOptions.odometry_sd)")
    slam.add_argument("--loop-growth", type=float, metavar="X",
                      help="loop-closure candidates' radius grows by X times the travel between the two submaps "
                           "(default 0.1, see SlamOptions.loop_growth)")
    slam.add_argument("--robust-kernel", type=float, metavar="SD",
                      help="width of the Cauchy kernel on every match's edge, in standard deviations (default 1.5, "
                           "see SlamOptions.robust_kernel)")
    slam.add_argument("--loop-consistency", action=argparse.BooleanOptionalAction,
                      help="let an accepted loop closure into the graph only when the closures near both its "
                           "frames do not mostly disagree (default), or every accepted one "
                           "(see SlamOptions.loop_consistency)")
    slam.add_argument("--jump-check", type=_number_or_off, metavar="X",
                      help="when the front end's match fails at an odometry step over X times the run's usual "
                           "ones, search for the scan around the previous one and bridge an odometry jump it "
                           "proves (default 3), or 'off' (see SlamOptions.jump_check)")
    slam.add_argument("--turn-edge", type=_number_or_off, metavar="RADIANS",
                      help="the front end charges walls off the other map's grid as unknown for a scan whose "
                           "odometry step turned more than this (default 1.047: 60 degrees), or 'off' (see "
                           "SlamOptions.turn_edge)")
    slam.add_argument("--front-end-levels", type=int, metavar="N",
                      help="pyramid levels of the front end's matches (default 2, see SlamOptions.scan_matcher)")
    slam.add_argument("--front-end-lookup", choices=("bilinear", "nearest"),
                      help="the front end's lookup of each wall's cost: blended between the four cell centres "
                           "around it (default) or the nearest cell's (the default before 2026-12-06, with 3 levels)")
    slam.add_argument("--loop-grid-edge", choices=("free", "unknown"),
                      help="what a wall of one submap costs in a loop closure's match where it lands off the other "
                           "submap's grid: nothing (default) or as on an unknown cell (fewer wrong closures on "
                           "exact truth; see SlamOptions.matcher and docs/slam.md)")
    slam.add_argument("--resolution", type=float, metavar="M", help="cell side, metres (default 0.05)")
    slam.add_argument("--max-ray", type=float, metavar="M", help="beams are cut there, metres (default 20)")
    slam.add_argument("--free-margin", type=float, metavar="M",
                      help="the submaps' beams are free only up to M metres short of their returns (default 0.1)")
    slam.add_argument("--max-range", type=float, metavar="M",
                      help="a CARMEN log's sensor maximum: a reading at or above it is no return (default: the "
                           "largest reading that is the largest of two scans or more)")
    slam.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    slam.set_defaults(func=_slam)
    args = parser.parse_args(argv)
    if getattr(args, "trials", 1) < 1 or getattr(args, "covariance_trials", 2) < 2:
        parser.error("--trials must be >= 1 and --covariance-trials >= 2")
    if getattr(args, "g2o", None) is not None and min(args.g2o) < 0:
        parser.error(f"--g2o takes two vertex ids >= 0; got {args.g2o[0]} {args.g2o[1]}")
    if getattr(args, "degrees", False) and args.command != "align-many":
        name = "initial" if args.command == "align" else "pose"
        if getattr(args, name) is None:
            parser.error(f"--degrees needs --{name}: it says how to read --{name}'s THETA")
        setattr(args, name, [*getattr(args, name)[:2], math.radians(getattr(args, name)[2])])
    from taichi_match import TaichiMatchError

    try:
        if args.command in ("align", "merge") and args.plot:
            _check_picture(args)
        return args.func(args)
    except KeyboardInterrupt:
        print("taichi-match: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:                      # the reader went away (| head): nothing more to say
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except (TaichiMatchError, ValueError, OSError) as exc:
        print(f"taichi-match: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except MemoryError:
        print("taichi-match: error: out of memory (the maps or the options ask for more than this machine has)",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:                     # a safety net: one line, never a traceback
        print(f"taichi-match: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())
