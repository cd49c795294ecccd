"""The mapping loop: 2-D laser scans with odometry in, a corrected trajectory and a map out.

Apart from the core (which never imports it); the pose graph needs ``gtsam`` (the ``slam`` extra).

Front end. Scans are grouped into submaps of ``submap_scans`` consecutive scans, a new one
starting every ``submap_scans // 2`` scans, so that every scan lies in two submaps and a submap
is half full when the next one starts (as in Cartographer). Each scan is matched against the
older of the two open submaps, which then holds at least half its scans: the scan as map B (its
beams cast alone, with a decisive hit/miss model so that its rays are free and its returns
walls), the submap as map A (its scans cast at their current estimates, in the submap's own
frame, each beam free only up to ``free_margin`` short of its return), from the odometry's
guess, with ``scan_matcher``'s options. Free space along the rays counts against the submap's
walls: the matcher's negative information. A match that passes ``scan_accepted`` and agrees
with the odometry's prediction (a 99.9 % chi-square gate on the step's covariance plus
``gate_inflation`` times the match's) gives the scan's pose and an edge from the submap's frame
to the scan with the match's calibrated covariance; otherwise the scan keeps the odometry's
prediction, and the open submaps leave it out until the next optimisation has placed it: at a
corner that prediction can be degrees off, and the scans matched against it inherited the
error (traced on the simulated run; over three jittered runs each, the median ATE fell on the
simulated run and 7 of the 8 logs, csail rose from 0.107 to 0.116 m, and aces and orebro no
longer derail: bench/SLAM.md).

Submap frames. A submap's frame is a node of its own in the graph (``submap_frames``, the
default), which starts at its first scan's (the anchor's) estimate, or, with
``submap_frames=False``, the anchor's node itself. A match against a submap's grid measures where
the grid lies, and the grid is all its scans cast at their estimates in the frame: tying the match
to one scan's node bakes that scan's error into every edge through it (on the simulated run, an
anchor at a 92-degree turn was 2.5 degrees off its submap's other scans, and seven loop closures
through it held it there). A scan of the submap that no match against it measured is tied to the
frame by a member edge: their relative pose as estimated when the scan joined, with the odometry
model's uncertainty of that displacement, under the Cauchy kernel, so the frame settles where most
of its scans say (as Cartographer's submap nodes do). Over twenty runs per log
(bench/SLAM_before_gate_inflation.md against bench/SLAM_before_submap_frames.md) frames brought
145 runs of 180 within the ATE target instead of 139, a quarter to a half of the loop closures
wrong against the references and a crisper map on every log, for a higher RPE over 10 scans in
degrees on seven logs (mostly won back by ``gate_inflation`` 2) and 1.2-1.6 times the
optimisation's time.

Back end. A pose graph over all scans and submap frames (``gtsam``): odometry edges between
consecutive scans (covariance from ``odometry_sd``), the front end's scan-to-submap edges, member
edges and loop closures. When a submap is complete it is matched against every earlier complete
submap that shares no scan with it and whose frame lies within ``loop_radius`` plus
``loop_growth`` times the distance travelled between the two, from the relative pose of the
current estimates (candidates sharing almost no known cells at that guess, ``LOOP_MIN_OVERLAP``,
or whose walls meet fewer than ``LOOP_MIN_WALLS`` known cells of the other there, are not
matched). The earlier submap is matched as cast at the current estimates: when the graph
has moved one of its scans in its frame by more than ``RECAST_CELLS`` or ``RECAST_RAD`` since it
was last cast (later loop closures straighten old submaps), it is cast again first, so that the
match sees the submap the graph now believes in and the edge's frame is the frame's current
estimate (bench/SLAM.md at 450a9e0 against the revision before, median ATE over five runs per log: orebro
0.175 -> 0.118 m, edmonton 0.169 -> 0.161, fhw 0.147 -> 0.143, freiburg-101 0.064 -> 0.059, the
others within 0.006 m; no aces run derailed, one in five did; the simulated run's loop closures
wrong against its truth 17 of 133 -> 11 of 140; casting every candidate again instead was worse
on four logs of six); accepted matches become edges between the frames, unless the loop closures
already in the graph whose frames both lie within ``NEIGHBOUR_PATH`` metres of travel of the new
one's mostly disagree with it: each predicts the new relative pose through the current
estimates' short chains between the frames
(their uncertainty from the odometry model, conservative) and agrees when within 3 sd (pairwise
consistency, as in PCM). A candidate whose guess lies beyond the matcher's basin can converge
onto an aliased pose: on aces, guesses 1.6-2.2 m and 6 degrees off in a corridor gave three
accepted closures 1.2-2 m off that agreed with each other and derailed a run (ATE 0.86 m); with
the vote 0.23 m, and every other run of bench/SLAM.md unchanged. Every match's edge
(scan-to-submap and loop closure) is under a Cauchy kernel, against the wrong matches that still
get through (a scan turning a corner can slide several degrees on the junction's few walls), and
at the end a loop closure that the optimised graph contradicts (``loop_gate``) leaves it. The
graph is optimised (Levenberg-Marquardt, or with ``solver`` "isam2" incrementally) each time a
submap is complete, and once more at the end (Levenberg-Marquardt); the estimates are replaced. A
new submap's candidates are all chosen (and cast again) first, then matched, this process taking
them from the front while helper processes (``workers``, ``_helper``) take them from the end,
then judged in order: the same results as matching them one by one here, bit for bit. With
``loop_ties`` each is decided and matched in turn instead.

Audit. After the last optimisation the complete submaps are compared pairwise at their optimised
poses with the verdict's wall test (``audit``): a pair whose walls land on each other's free space
*disagrees*, the mark of a place mapped twice apart; with "repair" (the default) each such pair
that no loop closure joins is matched after a search around the graph's relative pose, and the
accepted matches enter the graph as loop closures before a last optimisation (a derailed aces run,
1.30 m, came back at 0.08 m; docs/slam.md).

Scan by scan. ``Slam.add(scan)`` runs the loop for one more scan, as on a robot, and returns its
pose as estimated then; ``Slam.finish()`` ends the run (the last submap's loop closures, the last
optimisation, the audit, the map). ``Slam.run(log)`` checks the whole log first, then does exactly
that. Everything happens in the caller's thread: a scan that completes a submap waits for its loop
closures and an optimisation (``SlamResult.add_seconds``; bench/SLAM.md gives each log's spread).

Frames: the world frame is the odometry frame of the first scan (its first pose is kept);
poses are the laser's (x, y, theta), metres and radians. ``SlamResult.poses``: every scan's pose.
Graph keys: scan k is key k; with ``submap_frames`` submap i's frame is key ``FRAME_KEY`` + i (2**30
+ i: clear of any scan's key, and within the 32-bit ids g2o's tools read), so frames need no
knowledge of the log's length and ``add`` runs them as ``run`` does.
"""

import math
import time
from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np

from . import _pose_graph as pose_graph
from ._errors import InvalidMapError, InvalidOptionError, SlamRunError, shown
from ._grid import GridMap, cells
from ._helper import Helper
from ._matcher import AMBIGUITY, Matcher
from ._options import MatchOptions
from ._se2 import compose, inverse, transform_points, wrap_angle
from ._slam_outputs import jump_summary, loop_summary, output_paths, report, scan_times, write_outputs
from ._verdict import MAX_CONFLICT, MIN_AGREEMENT, MIN_WALLS, compare_walls, placed_walls, wall_statistics
from .logs import MAX_ANGLE, MAX_COORDINATE, LaserLog, Scan
from .scans import BeamCounts, SensorModel, beam_segments, scans_to_grid

__all__ = ["SlamOptions", "SlamResult", "Slam", "slam", "output_paths", "write_outputs", "report", "loop_summary",
           "scan_times", "scan_accepted", "jump_summary"]

# One scan alone: a return is a wall, a ray free (log-odds +-2: p 0.88 / 0.12, beyond the
# trinary thresholds that the default model's single observation, +0.9 / -0.4, falls between).
SCAN_MODEL = SensorModel(hit=2.0, miss=-2.0)

# A scan-to-submap match becomes an edge when the matcher converged and, of the verdict's
# evidence (``_verdict``), the walls agree and do not conflict as for map pairs, with fewer walls
# (a scan of 180 beams compares 30-120) and a larger uncertainty allowed: a lone scan's
# calibrated standard deviation is typically 4-7 cm, which its edge's covariance carries into the
# graph, where odometry and the other scans outweigh it.
SCAN_MIN_WALLS = 20
MIN_CELLS_PER_RAY = 20           # max_ray_length / resolution, at least
# ... and at most: a submap's canvas spans up to 2 max_ray_length / resolution cells a side, (2 x
# 4096)^2 = 67 M cells of int32 counts (half a GB) and their grids (at 20 m rays and 0.002 m cells a
# run held 9.8 GB before the counts' own limit refused it)
MAX_CELLS_PER_RAY = 4096
# The factors that scale a covariance (``robust_kernel``, ``front_end_inflation``,
# ``gate_inflation``) lie in this range, and the odometry's standard deviations at most ODOMETRY_SD_MAX,
# its floors at least ODOMETRY_SD_MIN: 1e308 or 1e-308 passed every "finite and > 0" check and wrote
# NaN and inf information matrices into graph.g2o (a red-team pass, 2026-12-07)
SCALE_RANGE = (1e-6, 1e6)
ODOMETRY_SD_MAX = 1e3
ODOMETRY_SD_MIN = 1e-9
ODOMETRY_GATE = 16.27            # chi-square, 3 degrees of freedom, 99.9 %
# ``jump_check``: a front-end match that fails at an odometry step beyond ``jump_check`` times the
# median of the last JUMP_STEPS steps, and beyond JUMP_FLOOR_M metres or JUMP_FLOOR_RAD radians
# (a robot turning on the spot makes steps of a few centimetres), is searched for again around
# the previous scan (``Slam._check_jump``)
JUMP_STEPS = 100
JUMP_FLOOR_M = 0.5
JUMP_FLOOR_RAD = 0.5
SCAN_MAX_UNCERTAINTY_M = 0.15
NEIGHBOUR_PATH = 15.0            # metres of travel: loop closures this close at both ends vote
# A loop-closure candidate is matched only when at least this share of the new submap's known
# cells (every 5th) lands on known cells of the older one at the guess (0.36 ms a check on cached
# footprints). Over the eight shared logs at default options (2026-12-03), of the candidates
# matched at a threshold of 0.01, those sharing 0.01-0.03 were 218 of 2,693 and gave one accepted
# closure (seattle's, wrong against the reference), those sharing 0.03-0.05 gave 5 of 135 (3
# right). Below 0.01 (measured before): 37-48 % of the candidates within the radius on fhw, csail
# and aces, none accepted, a third of the loop-closing time.
LOOP_MIN_OVERLAP = 0.03
# A loop-closure candidate is matched only when at least this many walls of the two submaps land on
# each other's known cells at the guess (the verdict's count, which must reach ``MIN_WALLS``, 50,
# for a match to be accepted; a match moves the walls by the guess's error). Over every candidate
# of a run on fhw, freiburg-101 and aces at default options (2026-12-08), the accepted matches had
# 30-48 walls at their guesses at least (5th percentile 78-135); those under 20 were 99 of 790 on fhw
# (0.55 s of matching), 6 of 305 and 126 of 365, none accepted. A candidate turned down never
# enters the graph, so a run whose skipped candidates would all have been turned down keeps every
# bit (the nine runs at seed 0 of bench/slam.py did; not a guarantee: a match can gain walls).
LOOP_MIN_WALLS = 20
# An older submap is cast again before a loop-closure match when the graph has moved one of its
# scans, in its frame, by more than this many cells along x or y or this many radians since its
# last cast (module docstring). On the simulated run 21 casts again for 168 candidates, on fhw 148
# for 837.
RECAST_CELLS = 0.5
RECAST_RAD = 0.0035                # 0.2 degree
# A searched loop closure's angle window: its translation window over this many metres (an
# angle error that moves a wall this far off by the translation window). On aces a long loop left
# guesses 1.6-2.3 m and 3-6 degrees off: 0.046-0.03 rad per metre, 0.1 here.
LOOP_SEARCH_ARM = 10.0
# ... and at most this many metres: on aces the guesses after the long loop were 1.6-2.3 m off;
# the drift bound (``loop_growth`` times the distance travelled) reaches 10 m and more, whose
# windows took seconds per candidate on laser submaps (a run of aces did not end in 20 minutes).
LOOP_SEARCH_MAX = 2.5
# Two complete submaps that share no scan *disagree* at the optimised poses when at least
# ``_verdict.MIN_WALLS`` of their walls land on each other's known cells, under this share of them
# within ``AGREE_CELLS`` of a wall of the other, and over that share on free space beyond
# ``CONFLICT_CELLS`` (``audit``). Measured at the final poses of one run per log (2026-12-04): pairs
# of every run within the ATE target at most 0.62 conflict and at least 0.27 agreement (csail),
# 0.16-0.19 agreement on six pairs of edmonton's (0.47 at the reference poses: ours are off there),
# and four pairs of belgioioso's at 0.96-1.0 conflict (0.88-0.90 at the reference poses too: the
# place changed between the visits); the derailed aces run (ATE 1.30 m), 80 pairs at up to 1.0.
DISAGREE_AGREEMENT = 0.25
DISAGREE_CONFLICT = 0.5
AUDITS = (None, "report", "repair")
NO_BEAM = "no usable beam in the scans (all readings invalid)"
NO_ODOMETRY = ("the log has no odometry (every scan carries the same pose); the mapping loop needs it for its "
               "guesses")
# With ``crop_target``, the front end's target is cast only within the box the scan's grid covers
# at the guess, widened by this many metres plus this many radians times the farthest corner of
# the scan's grid from the scan (where a rotation moves it most): a match that moves farther from
# the odometry's guess fails the odometry gate anyway.
CROP_METRES = 1.0
CROP_RADIANS = 0.05
MAX_WORKERS = 64
# ``loop_ties``: this many candidates of a new submap are matched, tied or not, before tied ones are
# left (with none, tied frames left aces too few closures: 3 runs in 5 derailed, 1.4-2.9 m; with 6
# the median ATE over five runs rose on seven shared logs of nine, aces 0.123 -> 0.176 m; with 10 on
# two: bench/SLAM_loop_ties.md)
LOOP_TIE_FREE = 10
# ``submap_frames``: submap i's frame is graph key FRAME_KEY + i (module docstring)
FRAME_KEY = 1 << 30


def scan_accepted(result) -> bool:
    """Whether a scan-to-submap match is kept (see ``SCAN_MIN_WALLS``)."""
    ev = result.evidence
    return bool(result.converged and ev.walls_compared >= SCAN_MIN_WALLS and ev.wall_agreement >= MIN_AGREEMENT
                and ev.wall_conflict <= MAX_CONFLICT and ev.uncertainty <= SCAN_MAX_UNCERTAINTY_M)


@dataclass(frozen=True)
class SlamOptions:
    """Settings of the mapping loop (``Slam``, ``slam``; the module docstring describes the loop).

    Every field is checked when the options are made: a value out of its range, of the wrong type or
    in a combination the loop cannot run raises ``InvalidOptionError`` saying which and why. The
    measurements behind each default, and the alternatives tried, are in docs/slam.md ("The mapping
    loop: what was measured, option by option").

    Parameters
    ----------
    resolution : float, default 0.05
        Cell side of the submaps and the final map, metres: finite and > 0, with
        ``max_ray_length / resolution`` from ``MIN_CELLS_PER_RAY`` (20) to ``MAX_CELLS_PER_RAY`` (4096)
        cells. The audit's test counts cells, so it loosens at coarse resolutions (``audit``). The
        default: 0.1 m cells ruined the trajectories (docs/slam.md, "The front end's 5 ms, at a coarser
        grid").
    submap_scans : int, default 10
        Scans per submap, an even integer >= 4; a new submap starts every ``submap_scans // 2`` scans,
        so that every scan lies in two submaps. The default: 16 derailed aces, and 8 or 6 made loop
        closing longer with more wrong closures (docs/slam.md).
    target_refresh : int, default 1
        The front end's target (the older open submap) is cast and prepared again after this many
        scans, and whenever it changes or the graph was optimised: 1 casts it for every scan (with the
        scan before it); ``submap_scans // 2`` or more casts it once per submap, when it becomes the
        target. An integer >= 1 (not a bool). ``crop_target`` needs 1. The default: 5 is faster but raised
        orebro's and edmonton's ATE, and 2 edmonton's (docs/slam.md).
    share_coarse : bool, default False
        When the front end's target is cast again within one submap (``target_refresh``), only its
        finest level is prepared anew and its coarser pyramid levels are those of its cast when it
        became the target (``Matcher.prepare(coarse_from=...)``; cast whole again after each
        optimisation). True or False; not with ``crop_target``. Off by default: faster, but fewer runs
        within the ATE target, since the coarse levels bring a scan into the basin and their latest
        scans count (docs/slam.md, "`share_coarse` with today's defaults").
    crop_target : bool, default False
        Cast the front end's target for each scan only around where the scan can land: the box its grid
        covers at the odometry's guess, widened by ``CROP_METRES`` and ``CROP_RADIANS``
        (``footprint_bounds``), so that the target's preparation follows the scan's reach, not the
        submap's size. True or False; it needs ``target_refresh`` 1 and ``share_coarse`` False, or
        ``InvalidOptionError``. Off by default: it spares little where scans cover most of their submap
        (edmonton) and fewer runs met the ATE target (docs/slam.md, "`crop_target` with today's
        defaults").
    max_ray_length : float, default 20.0
        Beams are cut there (metres) in submaps and scans: finite and > 0, longer than ``free_margin``,
        and ``max_ray_length / resolution`` from 20 to 4096 cells (``resolution``). An odometry step
        longer than this between two scans is refused with ``InvalidOptionError`` before any work
        (``Slam.run`` checks the whole log first, ``Slam.add`` each scan): the scans cannot overlap.
        The default: 30 m was slower with the ATE higher on some logs, 25 m derailed aces, and 15 m
        raised the ATE on three logs of four (docs/slam.md).
    free_margin : float, default 0.1
        The submaps' and the final map's beams count as free only up to this many metres short of their
        returns (``SensorModel.free_margin``; a lone scan's own grid is not cut). A wall seen by several
        scans is a band of cells: without the margin the beams landing long clear the cells of those
        landing short, and a submap's walls move away from the lasers that saw them. Finite, >= 0 and
        shorter than ``max_ray_length``. The default: it cut the front end's forward bias and lowered the
        median ATE on eight logs of nine, where 0.15 raised edmonton's and orebro's and 0.125 derailed a
        simulated run (docs/slam.md, "The submaps' free margin").
    odometry_sd : tuple of 5 float, default (0.02, 0.02, radians(0.3), 0.005, radians(0.1))
        (metres per metre travelled, radians per radian turned, radians per metre, metres floor,
        radians floor): the standard deviations of an odometry step's translation (each axis: metres
        per metre times the distance, plus the metres floor) and rotation (radians per radian times the
        turn, plus radians per metre times the distance, plus the radians floor), for the odometry
        edges and the odometry gate, the member edges (``submap_frames``) and the neighbours' vote
        (``loop_consistency``). Five finite numbers in [0, ``ODOMETRY_SD_MAX``] (1e3), the two floors at
        least ``ODOMETRY_SD_MIN`` (1e-9). The default: doubled or halved, a log derailed (docs/slam.md,
        "The odometry model").
    loop_radius, loop_growth : float, default 3.0 and 0.1
        A submap pair is a loop-closure candidate when their frames lie within ``loop_radius +
        loop_growth * distance travelled between them`` (metres); both finite and >= 0.
        ``loop_growth * distance travelled`` is also the drift bound of ``loop_search`` and of the
        audit's repair searches. The default radius: 5 and 8 m each raised the ATE on some logs, 8 also
        the wrong closures (docs/slam.md, "A wider loop-closure radius").
    loop_search : float or None, default None
        When ``loop_growth * distance travelled`` between a candidate's submaps (the drift its guess may
        carry) exceeds this many metres, beyond the local matcher's basin, the match first searches a
        window of that many metres (at most ``LOOP_SEARCH_MAX``) and ``LOOP_SEARCH_ARM`` times fewer
        radians around the guess (``search_window``, issue 13); None: never. Otherwise finite and >= 0.
        None by default: with 0.5 no aces run derailed, but three logs got worse and the loop took twice
        the time per scan (docs/slam.md).
    loop_ties : float or None, default None
        For long runs: once ``LOOP_TIE_FREE`` candidates of a new submap have been matched, a further
        one is not when the loop closures already in the graph (those judged just before it included)
        tie its two frames within this many metres: the travel along the trajectory on the shortest way
        between them that may cross closures (``tie_distances``). Revisits then cost a few matches
        each, not one per earlier pass. None: every candidate is matched. Otherwise finite and >= 0;
        it decides each candidate on the closures judged before it, so it needs ``workers`` 0. None by
        default: it keeps long runs' time per scan nearly flat, but on the short shared logs it raised
        aces' and fhw's median ATE (docs/slam.md).
    solver : {"batch", "isam2"}, default "batch"
        The pose graph's optimisation after each submap: "batch" (Levenberg-Marquardt over the whole
        graph, whose cost grows with it) or "isam2" (gtsam's incremental smoother given the new factors
        and nodes); the final optimisation is Levenberg-Marquardt either way. "batch" by default: iSAM2
        optimised in 0.3-0.5 of the time but had worse tails on three logs over twenty runs
        (docs/slam.md, "iSAM2 again").
    workers : int, default 0
        Helper processes that match a share of the loop-closure candidates while this one matches the
        others (``_helper``): the same results bit for bit. An integer from 0 to ``MAX_WORKERS`` (64);
        ``loop_ties`` needs 0. 0 by default: on a 2-core machine a helper did not pay (docs/slam.md).
    robust_kernel : float, default 1.5
        Width of the Cauchy kernel on every match's edge (scan-to-submap and loop closure), in standard
        deviations: wider trusts matches more. A number in ``SCALE_RANGE`` (1e-6 to 1e6). The default of
        the widths measured, 3, 1.5 and 1 (graduated non-convexity instead was not kept: docs/slam.md).
    front_end_inflation : float, default 6.0
        The front end's scan-to-submap edges enter the graph with this many times their match's
        calibrated covariance (the odometry gate uses ``gate_inflation`` times it; loop closures are
        not inflated): the scans matched against one submap share the error of that submap as cast,
        which the graph, taking their edges as independent, does not see. A number in ``SCALE_RANGE``.
        The default: with the bilinear lookup's own calibration, 6 keeps edmonton's edges as they were
        and brought more runs within the ATE target (docs/slam.md, "2026-12-06, later").
    gate_inflation : float, default 2.0
        The odometry gate compares a front-end match with the odometry's prediction using this many
        times the match's calibrated covariance (plus the odometry step's): a scan matched against a
        submap carries the error of the submap as cast, which the calibration (fitted on independent
        crops and cycles) does not hold. A number in ``SCALE_RANGE``. The default: of 1, 2 and 6, 2
        brought the most runs within the ATE target over twenty runs per log (docs/slam.md, "the
        odometry gate with twice the match's covariance").
    loop_consistency : bool, default True
        An accepted loop closure (the audit's repairs included) enters the graph only when the loop
        closures already there near both its frames do not mostly disagree with it (see the module
        docstring); False: every accepted one enters. True or False. On by default: aliased closures
        that agreed with each other derailed an aces run without it (module docstring).
    jump_check : float or None, default 3.0
        When the front end's match fails at an odometry step longer than this many times the median of
        the last ``JUMP_STEPS`` steps and than ``JUMP_FLOOR_M`` (or turning more than as many times
        theirs and than ``JUMP_FLOOR_RAD``), the scan is searched for in its target within that length
        of the previous scan's pose, as if the robot had not moved, and within that turn or as far as
        the odometry turned (``Slam._check_jump``). When the search finds it, proven and without a
        rival, away from the odometry's prediction and fitting clearly better there, and the scan
        placed on the scan before it by the odometry's step is not taken while by the found step it is
        (``Slam._scans_say_jump``), the odometry jumped: the scan takes the found pose and its edge,
        the odometry's step leaves the graph, and ``SlamResult.jump_checks`` says so (as do report.md
        and the command). A jump that returns at the next scan (one bad reading, a spike) is found as
        well, and the next scan is then matched from the step between the readings on either side of
        the bad one (``Slam._skipped_step``). Steps beyond ``max_ray_length`` are refused before any
        work. Not seen: a jump at the first steps, at a scan without a usable reading, within the run's
        usual steps and turns, or under ``JUMP_FLOOR_M`` and ``JUMP_FLOOR_RAD``. None: no check;
        otherwise finite and >= 1. On by default: it bridged 16 of 18 jumps planted into three logs and
        left the shared logs' trajectories the same bit for bit (docs/slam.md, "2026-12-07, later").
    turn_edge : float or None, default radians(60)
        A scan whose odometry step turned more than this many radians is matched by the front end
        with walls off the other map's grid charged as on its unknown cells (``MatchOptions.grid_edge``
        "unknown") instead of free. A scan's grid is the box around its beams; after a sharp turn the
        submap's walls behind the robot lie in that box's unknown corners, and turning the scan on
        carries them off the box, where they would cost nothing: on the simulated worlds 5 of 35
        right-angle turns were matched 1.4-5.3 degrees too far, and the submaps cast with them closed
        loops as far off. None: never; otherwise radians in [0, pi]. The default: over twenty runs
        per log the simulated run's wrong loop closures 3 -> 2 (median), the real logs within their
        spreads (146 runs of 180 within the ATE target both); at 45 degrees belgioioso lost three
        runs (docs/slam.md, "2026-12-07, late").
    loop_gate : float or None, default ODOMETRY_GATE (16.27)
        After the last optimisation (and the audit's repairs), each loop closure in the graph whose
        residual at the optimised poses, squared in its own covariance (the match's calibrated one, as
        the edge has it), exceeds this chi-square (3 degrees of freedom; 16.27 is 99.9 %) leaves the
        graph (as does one whose chi-square is not a number), which is then optimised once more
        (``Slam._gate_loops``): its record in ``SlamResult.loops`` gets "edge" False and "gated" True
        (every closure in the graph gets its "residual"), and its factor's slot in ``SlamResult.graph``
        is left empty. None keeps every one; otherwise finite and > 0. Under the Cauchy kernel
        (``robust_kernel`` 1.5) such an edge weighs at most an eighth of its Gaussian weight, so the
        poses hardly move; the graph (``graph.g2o``, whose readers have no robust kernel) no longer
        holds it. On by default: over twenty runs per log it left fewer wrong closures in the graph on
        six logs of nine and moved each run's ATE by millimetres (docs/slam.md, "2026-12-07, evening").
    audit : {"repair", "report", None}, default "repair"
        After the last optimisation, look for complete submaps that disagree at their optimised poses
        (``DISAGREE_AGREEMENT``, ``DISAGREE_CONFLICT``: walls of one on the other's free space), the
        map's self-check: "report" lists them in ``SlamResult.disagreements``; "repair" also matches
        each such pair that no loop closure joins after a search within ``loop_growth`` times the
        distance travelled between them (0.5-``LOOP_SEARCH_MAX`` metres, ``LOOP_SEARCH_ARM`` times
        fewer radians) around the graph's relative pose, records each match in ``loops`` ("repair":
        True), adds the accepted ones that pass the neighbours' vote (``loop_consistency``) to the
        graph as loop closures and optimises again; None: neither. The check casts again the submaps
        the graph moved. The test counts cells (``_verdict.AGREE_CELLS``, ``CONFLICT_CELLS``), so at
        coarse ``resolution`` it loosens; a place that changed between visits disagrees too (a
        disagreement is a place to look at, not proof of an error). "repair" by default: it mends a run
        derailed by loop closures the local matcher could not find, and left the other logs' spreads
        the same to within 0.01 m (docs/slam.md, "The repair").
    submap_frames : bool, default True
        Give each submap its own frame node in the graph (see the module docstring); False: a submap's
        frame is its first scan's node (the default before 2026-12-06). True or False. On by default:
        more runs within the ATE target, a quarter to a half of the wrong loop closures and a crisper
        map on every log (docs/slam.md, "2026-12-06, evening").
    matcher : MatchOptions, default MatchOptions(count_overlap=False)
        The ``MatchOptions`` of the loop-closure matches (and of the audit's and the helpers'); must be
        a ``MatchOptions``. Both matchers leave the overlap uncounted (``count_overlap=False``) by
        default: the loop reads the pose, covariance and verdict only. With ``grid_edge="unknown"`` a
        wall off the other submap's grid (the box around its beams) pays as on an unknown cell, and the
        box's edge no longer pulls a loop closure: fewer wrong closures, but fewer runs within the ATE
        target on the real logs (docs/slam.md, "The grid's edge is structure on laser submaps").
    scan_matcher : MatchOptions, default MatchOptions(levels=2, interpolation="bilinear", count_overlap=False)
        The ``MatchOptions`` of the front end's scan-to-submap matches (and of the jump check's
        searches); must be a ``MatchOptions``. By default the envelope with each wall's cost
        interpolated between the four cell centres around it (``interpolation="bilinear"``) on two
        pyramid levels: with the nearest cell's cost a single scan against its submap steps by a wall's
        worth between poses millimetres apart, and a match on one level then often stopped at its
        guess. The default: against the nearest cell on three levels, the front-end match took 0.79-0.83
        of its time with a lower RPE over 10 scans on most logs (docs/slam.md, "2026-12-06: the
        envelope looked up bilinearly").
    """

    resolution: float = 0.05
    submap_scans: int = 10
    target_refresh: int = 1
    share_coarse: bool = False
    crop_target: bool = False
    max_ray_length: float = 20.0
    free_margin: float = 0.1
    odometry_sd: tuple = (0.02, 0.02, math.radians(0.3), 0.005, math.radians(0.1))
    loop_radius: float = 3.0
    loop_growth: float = 0.1
    loop_search: Optional[float] = None
    loop_ties: Optional[float] = None
    solver: str = "batch"
    workers: int = 0
    robust_kernel: float = 1.5
    front_end_inflation: float = 6.0
    gate_inflation: float = 2.0
    loop_consistency: bool = True
    jump_check: Optional[float] = 3.0
    turn_edge: Optional[float] = math.radians(60.0)
    loop_gate: Optional[float] = ODOMETRY_GATE
    audit: Optional[str] = "repair"
    submap_frames: bool = True
    matcher: MatchOptions = field(default_factory=lambda: MatchOptions(count_overlap=False))
    scan_matcher: MatchOptions = field(default_factory=lambda: MatchOptions(levels=2, interpolation="bilinear",
                                                                            count_overlap=False))

    def __post_init__(self):
        if not (isinstance(self.target_refresh, int) and not isinstance(self.target_refresh, bool)
                and self.target_refresh >= 1):
            raise InvalidOptionError(f"target_refresh must be an integer >= 1; got {self.target_refresh!r}")
        for name in ("loop_consistency", "submap_frames", "share_coarse", "crop_target"):
            if not isinstance(getattr(self, name), bool):
                raise InvalidOptionError(f"{name} must be True or False; got {getattr(self, name)!r}")
        if self.crop_target and (self.target_refresh != 1 or self.share_coarse):
            raise InvalidOptionError("crop_target casts the front end's target around each scan: it needs "
                                     "target_refresh 1 and share_coarse False")
        if not (isinstance(self.submap_scans, int) and self.submap_scans >= 4 and self.submap_scans % 2 == 0):
            raise InvalidOptionError(f"submap_scans must be an even integer >= 4; got {shown(self.submap_scans)}")
        for name in ("resolution", "max_ray_length"):
            value = getattr(self, name)
            if not (_real(value) is not None and math.isfinite(value) and value > 0):
                raise InvalidOptionError(f"{name} must be a finite number > 0; got {shown(value)}")
        low, high = SCALE_RANGE
        for name in ("robust_kernel", "front_end_inflation", "gate_inflation"):
            value = getattr(self, name)
            if not (_real(value) is not None and low <= value <= high):
                raise InvalidOptionError(f"{name} must be a number in [{low:g}, {high:g}] (it scales a covariance); "
                                         f"got {shown(value)}")
        for name in ("matcher", "scan_matcher"):
            if not isinstance(getattr(self, name), MatchOptions):
                raise InvalidOptionError(f"{name} must be a taichi_match.MatchOptions; got "
                                         f"{type(getattr(self, name)).__name__}")
        if self.max_ray_length / self.resolution > MAX_CELLS_PER_RAY:
            raise InvalidOptionError(f"max_ray_length / resolution must be at most {MAX_CELLS_PER_RAY} (a submap's "
                                     f"canvas spans twice that many cells a side); got "
                                     f"{shown(self.max_ray_length)} m / {shown(self.resolution)} m")
        if self.max_ray_length / self.resolution < MIN_CELLS_PER_RAY:
            raise InvalidOptionError(f"max_ray_length / resolution must be at least {MIN_CELLS_PER_RAY} (a ray "
                                     f"across at least that many cells, or a scan holds too few walls to match); got "
                                     f"{shown(self.max_ray_length)} m / {shown(self.resolution)} m")
        if self.loop_gate is not None and not (_real(self.loop_gate) is not None and math.isfinite(self.loop_gate)
                                               and self.loop_gate > 0):
            raise InvalidOptionError(f"loop_gate must be None or a finite number > 0; got {shown(self.loop_gate)}")
        if self.turn_edge is not None and not (_real(self.turn_edge) is not None and 0 <= self.turn_edge <= math.pi):
            raise InvalidOptionError(f"turn_edge must be None or radians in [0, pi]; got {shown(self.turn_edge)}")
        if self.jump_check is not None and not (_real(self.jump_check) is not None
                                                and math.isfinite(self.jump_check) and self.jump_check >= 1):
            raise InvalidOptionError(f"jump_check must be None or a finite number >= 1; got {shown(self.jump_check)}")
        for name in ("loop_radius", "loop_growth", "free_margin"):
            value = getattr(self, name)
            if not (_real(value) is not None and math.isfinite(value) and value >= 0):
                raise InvalidOptionError(f"{name} must be a finite number >= 0; got {shown(value)}")
        if self.free_margin >= self.max_ray_length:
            raise InvalidOptionError(f"free_margin must be shorter than max_ray_length; got {shown(self.free_margin)} "
                                     f"m and {shown(self.max_ray_length)} m")
        if not (isinstance(self.workers, int) and not isinstance(self.workers, bool)
                and 0 <= self.workers <= MAX_WORKERS):
            raise InvalidOptionError(f"workers must be an integer in 0..{MAX_WORKERS}; got {shown(self.workers)}")
        if self.loop_ties is not None and not (_real(self.loop_ties) is not None and math.isfinite(self.loop_ties)
                                               and self.loop_ties >= 0):
            raise InvalidOptionError(f"loop_ties must be None or a finite number >= 0; got {shown(self.loop_ties)}")
        if self.solver not in pose_graph.SOLVERS:
            raise InvalidOptionError(f"solver must be one of {pose_graph.SOLVERS}; got {shown(self.solver)}")
        if not (self.audit is None or isinstance(self.audit, str)) or self.audit not in AUDITS:
            raise InvalidOptionError(f"audit must be one of {AUDITS}; got {shown(self.audit)}")
        if self.loop_ties is not None and self.workers:
            raise InvalidOptionError("loop_ties decides each candidate on the closures judged before it: it needs "
                                     "workers 0")
        if self.loop_search is not None and not (_real(self.loop_search) is not None and math.isfinite(self.loop_search)
                                                 and self.loop_search >= 0):
            raise InvalidOptionError(f"loop_search must be None or a finite number >= 0; got {shown(self.loop_search)}")
        try:
            sd = np.asarray(self.odometry_sd, dtype=np.float64)
        except (TypeError, ValueError):
            sd = np.full(0, np.nan)
        if (sd.shape != (5,) or isinstance(self.odometry_sd, (str, bytes)) or not np.all(np.isfinite(sd))
                or np.any(sd < 0) or np.any(sd > ODOMETRY_SD_MAX) or np.any(sd[3:] < ODOMETRY_SD_MIN)):
            raise InvalidOptionError(f"odometry_sd must be 5 numbers in [0, {ODOMETRY_SD_MAX:g}], the last two (the "
                                     f"floors) at least {ODOMETRY_SD_MIN:g}; got {shown(self.odometry_sd)}")


@dataclass
class SlamResult:
    """What ``Slam.run`` (or ``Slam.finish``) found.

    poses : (S, 3) every scan's optimised pose in the world frame.
    timestamps : (S,) the scans' own timestamps.
    map : the global map, every scan cast at its optimised pose.
    graph, values : the gtsam factor graph and its optimised values (keys: scan k is k, submap i's
        frame S + i). A loop closure ``loop_gate`` took out leaves its factor's slot
        empty: ``graph.at(i)`` is then None, and
        ``graph.size()`` still counts the slot (``graph.nrFactors()`` does not).
    frames : (M, 3) each submap's frame in the world frame (submap i starts at scan
        i * ``submap_scans // 2``).
    scan_matches : (accepted, tried) front-end matches.
    loops : one dict per loop-closure candidate tried (helper: matched by a helper process
        (``workers``), submaps, frames: their graph keys,
        anchors: their first scans, members: each submap's (scans, poses in its frame) as cast
        for the match, accepted by the verdict, edge: also in the graph, votes: (agree, disagree)
        of its neighbours when they were asked, pose, repair: matched by ``audit`` "repair",
        factor: the index of its edge in ``graph``; with ``loop_gate``, for each that was in the
        graph at the end, residual: its chi-square at the optimised poses, and gated: whether that
        took it out (its edge then False), ...).
    scans : one dict per scan after the first (scan, submap: the index of the one it was matched
        against, pose in that submap's frame, accepted
        by the verdict, edge: also within the odometry gate, covariance; pose and covariance None
        when the scan or its submap has no usable reading and was not matched).
    seconds : wall time per stage.
    match_seconds : each front-end match's time, preparing its target (when cast anew) and its
        scan included.
    match_parts : (T, 3) the same in parts: preparing the target, preparing the scan, and the
        match of the two prepared maps (``MatchResult.seconds``), seconds.
    jump_checks : one dict per search ``jump_check`` made (scan; odometry_step; window: metres, radians;
        found: whether the search found the scan; step: where it found it, relative to the scan
        before, else None; jump: whether the odometry jumped there, so that its step left the
        graph; spike False), and one per scan after a jump matched from the scan before the jump
        instead (spike True: that jump was one bad reading; odometry_step from that scan, step
        where the match put it, relative to that scan; window None).
    add_seconds : (S,) each scan's ``Slam.add``, seconds (its front-end match, and when it
        completed a submap that submap's loop closures and an optimisation).
    disagreements : with ``audit``, one dict per pair of complete submaps that disagreed at the
        poses optimised before the audit (submaps, walls compared, agreement, conflict, repaired:
        whether a repair closure now joins them, in the final graph; with "repair" also joined:
        whether a loop closure in the graph joined them already, so no repair was searched; with
        ``loop_gate``, when it took out a closure, gated: whether one joining them was; ``poses``
        are those optimised again after the repair and the gate); None without ``audit``.
    """

    poses: np.ndarray
    timestamps: np.ndarray
    map: object
    graph: object
    values: object
    frames: np.ndarray
    scan_matches: tuple
    loops: list
    scans: list
    seconds: dict
    options: SlamOptions
    match_seconds: np.ndarray
    match_parts: np.ndarray
    loops_tied: int = 0
    loops_few_walls: int = 0
    disagreements: Optional[list] = None
    add_seconds: Optional[np.ndarray] = None
    jump_checks: list = field(default_factory=list)


class _Submap:
    def __init__(self, index, anchor, key):
        self.index = index
        self.anchor = anchor          # its first scan, where its frame starts
        self.key = key                # the graph key of its frame
        self.scans = []               # scan indices
        self.final_grid = None        # once complete: its scans cast at the estimates of its last cast
        self.final_poses = None       # (scans, poses in the frame) of that cast (``Slam._cast_final``)
        self.footprint = None         # its Footprint


class _ByKey:
    """Rows indexed by graph key, as a NumPy array's are by position: scan k's row at key k,
    submap i's frame's at ``FRAME_KEY`` + i; each part grows (doubling) as rows are set. Indexed
    by a key, a key and a column, a list or array of keys, or a slice (of the scans' rows)."""

    def __init__(self, tail=()):
        self._parts = [np.zeros((16,) + tail), np.zeros((4,) + tail)]        # scans', frames'

    def __getitem__(self, index):
        key, rest = (index[0], index[1:]) if isinstance(index, tuple) else (index, ())
        if isinstance(key, slice):
            return self._parts[0][(key,) + rest]
        keys = np.asarray(key, dtype=np.int64)
        if keys.ndim == 0:
            frame = int(keys) >= FRAME_KEY
            return self._parts[frame][(int(keys) - FRAME_KEY * frame,) + rest]
        frames = keys >= FRAME_KEY
        out = np.empty(keys.shape + self._parts[0].shape[1:])
        out[~frames] = self._parts[0][keys[~frames]]
        out[frames] = self._parts[1][keys[frames] - FRAME_KEY]
        return out[(slice(None),) + rest]

    def __setitem__(self, index, value):
        key, rest = (index[0], index[1:]) if isinstance(index, tuple) else (index, ())
        keys = np.asarray(key, dtype=np.int64)
        if keys.ndim == 0:
            frame = int(keys) >= FRAME_KEY
            row = int(keys) - FRAME_KEY * frame
            self._grown(frame, row)[(row,) + rest] = value
            return
        value = np.asarray(value, dtype=np.float64)
        for frame, chosen in ((0, keys < FRAME_KEY), (1, keys >= FRAME_KEY)):
            if chosen.any():
                rows = keys[chosen] - FRAME_KEY * frame
                self._grown(frame, int(rows.max()))[(rows,) + rest] = value[chosen] if value.ndim else value

    def _grown(self, part, row):
        old = self._parts[part]
        if row >= len(old):
            new = np.zeros((max(row + 1, 2 * len(old)),) + old.shape[1:])
            new[:len(old)] = old
            self._parts[part] = new
        return self._parts[part]


class _Mapping:
    """The state of one run of the mapping loop (``Slam.add``). Arrays indexed by scan (``odo``,
    ``usable``, ``castable``) grow as scans come; ``est`` and ``travelled`` are by graph key
    (``_ByKey``)."""

    def __init__(self, gtsam, options):
        self.gtsam = gtsam
        self.est = _ByKey((3,))                   # the scans' poses and the submaps' frames'
        self.travelled = _ByKey()                 # odometry path length up to each scan (a frame: its first scan's)
        self.odo = np.zeros((1, 3))
        self.usable = np.zeros(1, dtype=bool)  # whether a scan has a reading the submaps would cast
        self.castable = np.zeros(1, dtype=bool)    # scans the open submaps are cast from (module docstring)
        self.scans = []
        self.graph = gtsam.NonlinearFactorGraph()
        self.values = gtsam.Values()
        self.keys = []
        self.solver = pose_graph.Solver(gtsam, options.solver)
        self.submaps, self.done = [], []          # open (the older first), complete
        self.accepted = self.tried = 0
        self.loops, self.records, self.match_parts, self.add_seconds = [], [], [], []
        self.steps, self.jump_checks = [], []     # odometry steps (metres, radians turned); ``_check_jump``'s
        self.seconds = {"scan grids": 0.0, "submap grids": 0.0, "scan matching": 0.0, "loop closing": 0.0,
                        "optimisation": 0.0, "audit": 0.0, "final map": 0.0}
        self.target_cast = None                   # (submap, scan, grid): the front end's target as last cast
        self.coarse = None                        # its PreparedMap when cast whole (``share_coarse``)
        self.closed = False                       # whether the latest scan completed a submap
        self.broken = None                        # what broke the run part-way through a scan

    def optimise(self):
        """The whole graph optimised by Levenberg-Marquardt from ``values`` (whatever the solver):
        ``est`` and ``values`` follow it."""
        self.est[self.keys] = pose_graph.optimise(self.gtsam, self.graph, self.values, self.keys)
        self.values = pose_graph.values(self.gtsam, self.est, self.keys)

    def grow(self, size):
        """Room for ``size`` scans (doubling)."""
        if size > len(self.odo):
            for name in ("odo", "usable", "castable"):
                old = getattr(self, name)
                new = np.zeros((max(size, 2 * len(old)),) + old.shape[1:], dtype=old.dtype)
                new[:len(old)] = old
                setattr(self, name, new)


def _checked_scan(scan) -> Scan:
    """A copy of ``scan`` that ``Slam.add`` can map and keep (float64 arrays of its own, read-only:
    a driver may reuse its buffers), else InvalidOptionError saying why. Poses beyond the CARMEN
    reader's bounds (``logs.MAX_COORDINATE`` m, ``logs.MAX_ANGLE`` rad) are refused as it refuses them."""
    if not isinstance(scan, Scan):
        raise InvalidOptionError(f"a scan must be a taichi_match.logs.Scan; got {type(scan).__name__}")
    pose, ranges, angles = (_floats(v) for v in (scan.pose, scan.ranges, scan.angles))
    if (pose is None or pose.shape != (3,) or not np.all(np.isfinite(pose))
            or np.abs(pose[:2]).max() > MAX_COORDINATE or abs(pose[2]) > MAX_ANGLE):
        raise InvalidOptionError(f"a scan's pose must be three finite numbers (x, y, theta) within "
                                 f"{MAX_COORDINATE:g} m and {MAX_ANGLE:g} rad; got {shown(scan.pose)}")
    if ranges is None or angles is None or ranges.ndim != 1 or ranges.shape != angles.shape:
        raise InvalidOptionError(f"a scan's ranges and angles must be real numbers, 1-D of one length; got "
                                 f"{shown(scan.ranges)} and {shown(scan.angles)}")
    if not np.all(np.isfinite(angles)):
        raise InvalidOptionError("a scan's angles must be finite")
    timestamp, max_range = _real(scan.timestamp), _real(scan.max_range)
    if timestamp is None or not math.isfinite(timestamp):
        raise InvalidOptionError(f"a scan's timestamp must be a finite number; got {shown(scan.timestamp)}")
    if max_range is None or not max_range > 0:
        raise InvalidOptionError(f"a scan's max_range must be a positive number; got {shown(scan.max_range)}")
    for array in (pose, ranges, angles):
        array.flags.writeable = False
    return Scan(timestamp=timestamp, ranges=ranges, angles=angles, pose=pose, max_range=max_range)


def _real(value) -> Optional[float]:
    """``value`` as a float if it is a real number (not a bool, not complex) that a float holds."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        return None
    try:
        return float(value)
    except OverflowError:
        return None


def _floats(values) -> Optional[np.ndarray]:
    """``values`` as a new float64 array if they are real numbers (not bools, not complex)."""
    try:
        array = np.array(values)
    except (TypeError, ValueError, OverflowError):
        return None
    return array.astype(np.float64) if array.dtype.kind in "iuf" else None


class Slam:
    """The mapping loop (see the module docstring)."""

    def __init__(self, options: SlamOptions = None, **overrides):
        options = options if options is not None else SlamOptions()
        if not isinstance(options, SlamOptions):
            raise InvalidOptionError(f"options must be a taichi_match.slam.SlamOptions; got {type(options).__name__}")
        unknown = sorted(set(overrides) - set(SlamOptions.__dataclass_fields__))
        if unknown:
            raise InvalidOptionError(f"unknown SlamOptions field(s) {', '.join(unknown)}; the fields are "
                                     f"{', '.join(SlamOptions.__dataclass_fields__)}")
        self.options = replace(options, **overrides) if overrides else options
        self._matcher = Matcher(self.options.matcher)
        self._scan_matcher = Matcher(self.options.scan_matcher)
        self._scan_model = replace(SCAN_MODEL, max_ray_length=self.options.max_ray_length)
        self._map_model = SensorModel(max_ray_length=self.options.max_ray_length,
                                      free_margin=self.options.free_margin)
        self._counts = {}
        self._helpers = []
        self._mapping = None                  # the run under way (``add``)

    def _odometry_noise(self, gtsam, delta):
        return gtsam.noiseModel.Gaussian.Covariance(self._odometry_covariance(delta))

    def _robust_noise(self, gtsam, covariance):
        """A match's covariance under the Cauchy kernel (``robust_kernel`` standard deviations wide)."""
        gaussian = gtsam.noiseModel.Gaussian.Covariance(covariance)
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(self.options.robust_kernel),
                                              gaussian)

    def _match_edge(self, gtsam, graph, a, b, res, inflation: float = 1.0) -> int:
        """A match's edge from node ``a`` to node ``b``: its pose, its calibrated covariance times
        ``inflation`` under the Cauchy kernel. Returns its index in ``graph``."""
        cov = pose_graph.tangent_covariance(res.pose, res.calibrated_covariance) * inflation
        graph.add(gtsam.BetweenFactorPose2(a, b, gtsam.Pose2(*res.pose), self._robust_noise(gtsam, cov)))
        return graph.size() - 1

    def _odometry_covariance(self, delta):
        per_m, per_rad, rad_per_m, floor_m, floor_rad = self.options.odometry_sd
        d = math.hypot(delta[0], delta[1])
        sd_t = per_m * d + floor_m
        sd_r = per_rad * abs(delta[2]) + rad_per_m * d + floor_rad
        return np.diag([sd_t**2, sd_t**2, sd_r**2])

    def _odometry_glitch(self, m, k, target, scan_grid, res, gated, guess, delta):
        """Scan ``k``'s front-end match ``res`` (from ``guess``, the odometry's prediction in the
        target's frame; ``gated``: kept) when the odometry may have glitched: after a jump found
        at the scan before, also the match from the readings on either side of it (``_skipped_step``),
        kept when it passes its own odometry gate and fits better; then, if no match is kept at an
        unusual step (``_unusual_step``), the search for a jump (``_check_jump``). Returns (the
        match to keep instead, or None; the odometry's edge into scan k as (source scan, step), or
        None when the odometry jumped)."""
        est, edge = m.est, (k - 1, delta)
        skipped = self._skipped_step(m, k)
        if skipped is not None:
            start = compose(inverse(est[target.key]), compose(est[k - 2], skipped))
            other = self._scan_matcher.match(m.target_cast[2], scan_grid, start, grid_edge=res.options.grid_edge)
            if (scan_accepted(other) and self._agrees_with_odometry(other, start, est[k - 2], est[target.key], skipped)
                    and (not gated or other.residual < res.residual)):
                m.jump_checks.append({"scan": k, "odometry_step": skipped, "window": None, "found": True,
                                      "step": compose(inverse(est[k - 2]), compose(est[target.key], other.pose)),
                                      "jump": False, "spike": True})
                return other, (k - 2, skipped)
        window = None if gated else self._unusual_step(m)
        if window is not None:
            jumped = self._check_jump(m, k, target, scan_grid, res, guess, delta, window)
            if jumped is not None:
                return jumped, None
        return None, edge

    def _unusual_step(self, m):
        """When the latest odometry step is unusual (beyond ``jump_check`` times the median of the
        last ``JUMP_STEPS`` steps and the floors ``JUMP_FLOOR_M``, ``JUMP_FLOOR_RAD``), the search
        window (metres, radians): that usual length, and that usual turn or the step's turn and
        ``JUMP_FLOOR_RAD`` (at most pi); else None."""
        factor = self.options.jump_check
        if factor is None or len(m.steps) < 2:
            return None
        metres, radians = np.median(np.array(m.steps[-JUMP_STEPS - 1:-1]), axis=0)
        usual = max(factor * metres, JUMP_FLOOR_M), max(factor * radians, JUMP_FLOOR_RAD)
        step, turn = m.steps[-1]
        if step <= usual[0] and turn <= usual[1]:
            return None
        # as far as the odometry turned, too: a robot that turns at a corner between two scans (the
        # simulated run's 90 degrees) turned so, and its odometry's translation may have jumped
        return usual[0], min(max(usual[1], turn + JUMP_FLOOR_RAD), math.pi)

    def _skipped_step(self, m, k):
        """After a jump found before scan ``k - 1``: the odometry's step from scan ``k - 2`` to ``k``
        when it predicts scan ``k`` elsewhere than the step from ``k - 1`` does (more than
        ``JUMP_FLOOR_M`` or ``JUMP_FLOOR_RAD`` apart), as when scan ``k - 1``'s reading alone was
        bad (a spike, not a reset); else None."""
        checks = m.jump_checks
        if k < 2 or not checks or checks[-1]["scan"] != k - 1 or not checks[-1]["jump"]:
            return None
        odo, est = m.odo, m.est
        skipped = compose(inverse(odo[k - 2]), odo[k])
        through = compose(est[k - 1], compose(inverse(odo[k - 1]), odo[k]))
        return None if _same_place(compose(est[k - 2], skipped), through, JUMP_FLOOR_M, JUMP_FLOOR_RAD) else skipped

    def _check_jump(self, m, k, target, scan_grid, refused, predicted, delta, window):
        """Scan ``k``'s match (``refused``, from the odometry's prediction ``predicted``, both in
        the target's frame) failed at an unusual odometry step ``delta``: search for the scan in
        its target within ``window`` (metres, radians) of the previous scan's pose, as if the robot
        had not moved. The odometry jumped when the search finds a pose that ``scan_accepted``
        takes, proven and without a rival, within the window, more than ``JUMP_FLOOR_M`` or
        ``JUMP_FLOOR_RAD`` from the prediction, where the scan fits clearly better than the match
        from the prediction (its residual at most ``AMBIGUITY`` times that one's, or that one met
        fewer than ``SCAN_MIN_WALLS`` walls: at the robot's next pose a scan overlaps the scans
        before it, which its target holds; a guess 19 m off wandered away, its residual 0), and
        the scan before says so too (``_scans_say_jump``). Returns that match, or None, and
        records the check in ``jump_checks``."""
        start = compose(inverse(m.est[target.key]), m.est[k - 1])
        target_grid = m.target_cast[2]
        try:
            res = self._scan_matcher.match(target_grid, scan_grid, start, search_window=window)
        except InvalidMapError:                   # a map without walls: nothing to search with
            res = None
        found = (res is not None and scan_accepted(res) and res.search_complete is not False
                 and _same_place(res.pose, start, window[0] + JUMP_FLOOR_M, window[1] + JUMP_FLOOR_RAD) and not any(
                     # a runner-up scoring close to the best (the search's ambiguity, on lattice poses)
                     # is a rival only when a match from it is taken too, elsewhere, with a residual
                     # as close (the simulated building's corridor seen backwards: taken, its
                     # residual 0.274 against 0.187)
                     scan_accepted(other) and not _same_place(other.pose, res.pose)
                     and other.residual * AMBIGUITY <= res.residual
                     for other in (self._scan_matcher.match(target_grid, scan_grid, h.pose)
                                   for h in res.hypotheses[1:] if h.score >= AMBIGUITY * res.hypotheses[0].score)))
        step = compose(inverse(start), res.pose) if found else None
        jump = (found and not _same_place(res.pose, predicted, JUMP_FLOOR_M, JUMP_FLOOR_RAD)
                and (refused.evidence.walls_compared < SCAN_MIN_WALLS or res.residual <= AMBIGUITY * refused.residual)
                and self._scans_say_jump(m, k, scan_grid, delta, step))
        m.jump_checks.append({"scan": k, "odometry_step": np.array(delta), "window": window, "found": found,
                              "step": step, "jump": jump, "spike": False})
        return res if jump else None

    def _scans_say_jump(self, m, k, scan_grid, delta, step) -> bool:
        """Whether scan ``k`` placed on scan ``k - 1`` alone by the odometry's ``delta`` is not taken
        (fewer than ``SCAN_MIN_WALLS`` walls compared, too few agreeing or too many on free space:
        ``_verdict``) while placed by the found ``step`` it is: two consecutive scans overlap, and
        between them no submap's blur of several scans' errors (fhw, scan 57: its odometry step
        right to 1 cm and 0.5 degree, yet the scan matched its submap no better there than 3.2 m
        and 103 degrees away, where the search took it for a jump that left the run 9.7 m off)."""
        previous = scans_to_grid([m.scans[k - 1]], np.zeros((1, 3)), resolution=self.options.resolution,
                                 model=self._scan_model, evidence=self._scan_matcher.options.evidence)
        walls = self._scan_matcher.prepare(previous, levels=1).wall_distance
        own = self._scan_matcher.prepare(scan_grid, levels=1).wall_distance

        def taken(pose):
            compared, agreement, conflict = compare_walls(walls, own, placed_walls(walls, own, pose))
            return compared >= SCAN_MIN_WALLS and agreement >= MIN_AGREEMENT and conflict <= MAX_CONFLICT

        return not taken(delta) and taken(step)

    def _agrees_with_odometry(self, res, predicted, previous, anchor, delta):
        """Whether the match's pose (in the frame's) lies within the odometry step's uncertainty
        plus ``gate_inflation`` times the match's of the odometry's prediction (a 99.9 %
        chi-square gate): one step of odometry is far better than a lone scan that slid along a
        corridor or turned on a few walls."""
        # the step's covariance is in the previous scan's frame: rotate it into the anchor's
        c, s = math.cos(previous[2] - anchor[2]), math.sin(previous[2] - anchor[2])
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        cov = rot @ self._odometry_covariance(delta) @ rot.T + self.options.gate_inflation * res.calibrated_covariance
        d = np.asarray(res.pose, dtype=np.float64) - predicted
        d[2] = wrap_angle(d[2])
        return float(d @ np.linalg.solve(cov, d)) <= ODOMETRY_GATE

    def _usable(self, scan) -> bool:
        """Whether ``scan`` has a reading the submaps would cast."""
        return len(beam_segments([scan], np.zeros((1, 3)), self._map_model)[0]) > 0

    def _submap_grid(self, scans, submap, est, cast=None, bounds=None):
        """The front end's target: ``_cast_submap``'s grid, in the scan matcher's evidence."""
        grid, _ = self._cast_submap(scans, submap, est, cast, bounds, self._scan_matcher.options.evidence)
        return grid

    def _cast_submap(self, scans, submap, est, cast=None, bounds=None, evidence="probability"):
        """The submap's scans (those of ``scans`` with ``cast`` true) cast at their estimates in its
        frame: (grid, (scan indices, poses in the frame)). Between two optimisations the estimates stay put, so
        the beam counts of a submap cast before are kept (``_counts``) and only its scans not yet
        in them are cast: the same grid, bit for bit (``BeamCounts``), as casting them all.
        ``bounds``: only the grid's cells within that box of the frame (``BeamCounts.grid``);
        ``evidence`` "trinary": its trinary map, made from the counts directly (``BeamCounts.grid``)."""
        members = submap.scans if cast is None else [j for j in submap.scans if cast[j]]
        origin = inverse(est[submap.key])
        poses = compose(origin, est[np.array(members, dtype=np.int64)]).reshape(-1, 3)
        counts, added = self._counts.get(submap.index, (None, set()))
        if counts is None or not added.issubset(members):
            counts, added = BeamCounts(resolution=self.options.resolution, model=self._map_model), set()
            self._counts[submap.index] = (counts, added)
        new = [i for i, j in enumerate(members) if j not in added]
        counts.add([scans[members[i]] for i in new], poses[new])
        added.update(members[i] for i in new)
        return counts.grid(bounds, evidence=evidence), (members, poses)

    def _member_edge(self, gtsam, graph, submap, k, est):
        """The edge that ties scan ``k`` to the frame of a submap it lies in when no match of ``k``
        against that submap measured it: their relative pose as estimated now, with the odometry
        model's uncertainty of that displacement, under the Cauchy kernel."""
        rel = compose(inverse(est[submap.key]), est[k])
        graph.add(gtsam.BetweenFactorPose2(submap.key, k, gtsam.Pose2(*rel),
                                           self._robust_noise(gtsam, self._odometry_covariance(rel))))

    def run(self, log: LaserLog, progress=None) -> SlamResult:
        """Map ``log`` (its scans' poses are read as odometry); ``progress(k, n)`` after each scan.
        The whole log is checked first (each scan as ``add`` checks it, and the log as a whole:
        not empty, some odometry, some usable beam); then the same, bit for bit, as ``add`` for
        each scan and ``finish``."""
        if not isinstance(log, LaserLog):
            raise InvalidOptionError(f"the log must be a taichi_match.logs.LaserLog; got {type(log).__name__}")
        if self._mapping is not None:
            raise SlamRunError("a run of Slam.add is under way on this mapper: finish or close it first")
        scans = []
        for k, scan in enumerate(log.scans):
            try:
                scans.append(_checked_scan(scan))
            except InvalidOptionError as exc:
                raise InvalidOptionError(f"scan {k}: {exc}") from None
        n = len(scans)
        if n == 0:
            raise InvalidOptionError("the log holds no scan")
        odo = np.array([scan.pose for scan in scans])
        stamps = np.array([scan.timestamp for scan in scans])
        if n > 1 and not np.all(np.diff(stamps) > 0):
            raise InvalidOptionError("the scans' timestamps must increase (the trajectory's TUM file pairs poses "
                                     "by time)")
        if n > 1 and np.all(odo == odo[0]):
            raise InvalidOptionError(NO_ODOMETRY)
        steps = np.hypot(*np.diff(odo[:, :2], axis=0).T) if n > 1 else np.zeros(0)
        if len(steps) and steps.max() > self.options.max_ray_length:
            k = int(np.argmax(steps)) + 1
            self._check_step(k, odo[k - 1], odo[k])
        if not any(self._usable(scan) for scan in scans):     # before the loop, not at the final map
            raise InvalidOptionError(NO_BEAM)
        self._begin()
        try:
            for k, scan in enumerate(scans):
                self._add(scan)
                if progress is not None and k > 0:
                    progress(k + 1, n)
            return self.finish()
        finally:
            self.close()

    def add(self, scan: Scan) -> np.ndarray:
        """Map one more scan (its ``pose`` read as odometry; scans in time order): the mapping
        loop as it runs on a robot. Returns the scan's pose as estimated now (the front end's
        match, or the odometry's prediction; after an optimisation when this scan completed a
        submap). ``finish`` ends the run. A scan refused (InvalidOptionError: see
        ``_checked_scan``, and timestamps that do not increase, an odometry jump beyond a ray's
        reach) leaves the run as it was; any other error part-way breaks the run (then
        SlamRunError until ``close``). The scan is copied: its arrays may be reused."""
        return self._add(_checked_scan(scan))

    def _add(self, scan):
        m = self._mapping if self._mapping is not None else self._begin()
        self._check_unbroken()
        t_add = time.perf_counter()
        k = len(m.scans)
        if k and not scan.timestamp > m.scans[-1].timestamp:
            raise InvalidOptionError(f"the scans' timestamps must increase (the trajectory's TUM file pairs poses by "
                                     f"time): scan {k} at {scan.timestamp!r} after {m.scans[-1].timestamp!r}")
        if k:
            self._check_step(k, m.odo[k - 1], scan.pose)
        try:
            m.grow(k + 1)
            m.scans.append(scan)
            m.odo[k] = scan.pose
            m.usable[k] = m.castable[k] = self._usable(scan)
            if k == 0:
                self._first(m)
            else:
                self._step(m, k)
        except BaseException as exc:                     # the run is half-way through this scan
            m.broken = f"{type(exc).__name__} at scan {k}: {exc}"
            raise
        m.add_seconds.append(time.perf_counter() - t_add)
        return m.est[k].copy()

    def _check_unbroken(self):
        if self._mapping is not None and self._mapping.broken:
            raise SlamRunError(f"the run was broken part-way by {self._mapping.broken}; close() it and start again")

    def _check_step(self, k, before, after):
        step = math.hypot(after[0] - before[0], after[1] - before[1])
        if not step <= self.options.max_ray_length:
            raise InvalidOptionError(f"the odometry jumps {step:.1f} m between scans {k - 1} and {k}, farther than a "
                                     f"ray reaches (max_ray_length {self.options.max_ray_length:g} m): the scans "
                                     f"cannot overlap, and a submap across the jump would be mostly empty; the "
                                     f"odometry is broken there (split the log)")

    @property
    def poses(self) -> np.ndarray:
        """(S, 3) the current estimates of the scans added so far (world frame)."""
        m = self._mapping
        return np.zeros((0, 3)) if m is None else m.est[:len(m.scans)].copy()

    def current_map(self) -> GridMap:
        """The map of the scans added so far, each cast at its current estimate (``finish``'s
        global map, made now: about 0.2-0.7 ms a scan on the shared logs)."""
        self._check_unbroken()
        m = self._mapping
        if m is None or not m.usable[:len(m.scans)].any():
            raise InvalidOptionError("no usable scan was added: no map yet")
        return scans_to_grid(m.scans, m.est[:len(m.scans)], resolution=self.options.resolution, model=self._map_model)

    def _begin(self):
        """A new run."""
        gtsam = pose_graph.import_gtsam()
        self._helpers = [helper for helper in (Helper.start(self._matcher.options)
                                               for _ in range(self.options.workers)) if helper]
        self._mapping = _Mapping(gtsam, self.options)
        self._counts = {}             # submap index -> (BeamCounts, scans counted), since the last optimisation
        self._tied = 0                          # loop-closure candidates not matched: already tied
        self._few = 0                           # ... too few walls compared at the guess
        return self._mapping

    def close(self):
        """End the run without a result (and the helper processes)."""
        for helper in self._helpers:
            helper.close()
        self._helpers = []
        self._mapping = None

    def _first(self, m):
        gtsam = m.gtsam
        m.est[0] = m.odo[0]
        prior = gtsam.noiseModel.Diagonal.Sigmas(np.full(3, 1e-6))
        m.graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*m.est[0]), prior))
        m.values.insert(0, gtsam.Pose2(*m.est[0]))
        m.keys.append(0)
        self._open_submap(m, 0)

    def _step(self, m, k):
        """Scan ``k`` (after the first): its front-end match, its node and edges, and when it
        completes the older open submap, that submap's loop closures and an optimisation."""
        gtsam, opts, est, seconds = m.gtsam, self.options, m.est, m.seconds
        odo, usable, castable = m.odo, m.usable, m.castable
        delta = compose(inverse(odo[k - 1]), odo[k])
        m.steps.append((math.hypot(delta[0], delta[1]), abs(wrap_angle(delta[2]))))
        pred = compose(est[k - 1], delta)
        target = m.submaps[0]                             # the older open submap
        guess = compose(inverse(est[target.key]), pred)   # the scan's pose in the target's frame
        res = None
        # a scan without one usable reading (or a submap of such scans) is not matched
        if usable[k] and castable[target.scans].any():
            t0 = time.perf_counter()
            scan_grid = scans_to_grid([m.scans[k]], np.zeros((1, 3)), resolution=opts.resolution,
                                      model=self._scan_model, evidence=self._scan_matcher.options.evidence)
            t1 = time.perf_counter()
            preparing = 0.0                               # preparing the target: the match's time
            whole = m.target_cast is None or m.target_cast[0] is not target
            if opts.crop_target:                          # None: the scan cannot land on the submap
                cropped = self._submap_grid(m.scans, target, est, castable, footprint_bounds(scan_grid, guess))
                m.target_cast = None if cropped is None else (target, k, cropped)
            elif whole or k - m.target_cast[1] >= opts.target_refresh:
                m.target_cast = (target, k, self._submap_grid(m.scans, target, est, castable))
            if m.target_cast is not None and m.target_cast[1] == k:
                t = time.perf_counter()
                shared = None if whole or not opts.share_coarse else m.coarse
                prepared = self._scan_matcher.prepare(m.target_cast[2], coarse_from=shared)
                m.coarse = prepared if whole else m.coarse
                preparing = time.perf_counter() - t
            t2 = time.perf_counter()
            if m.target_cast is not None:
                self._scan_matcher.prepare(scan_grid)
                t3 = time.perf_counter()
                turning = opts.turn_edge is not None and abs(wrap_angle(delta[2])) > opts.turn_edge
                res = self._scan_matcher.match(m.target_cast[2], scan_grid, guess,
                                               **({"grid_edge": "unknown"} if turning else {}))
                m.match_parts.append((preparing, t3 - t2, res.seconds))
                m.tried += 1
            seconds["scan grids"] += t1 - t0
            seconds["submap grids"] += t2 - t1 - preparing
            seconds["scan matching"] += time.perf_counter() - t2 + preparing
        verdict = res is not None and scan_accepted(res)
        gated = verdict and self._agrees_with_odometry(res, guess, est[k - 1], est[target.key], delta)
        edge = (k - 1, delta)                             # the odometry's edge into scan k
        if res is not None:
            t = time.perf_counter()
            rescued, edge = self._odometry_glitch(m, k, target, scan_grid, res, gated, guess, delta)
            if rescued is not None:
                res, verdict, gated = rescued, True, True
            seconds["scan matching"] += time.perf_counter() - t
        if edge is not None:                              # None: the odometry jumped into scan k
            source, step = edge
            m.graph.add(gtsam.BetweenFactorPose2(source, k, gtsam.Pose2(*step), self._odometry_noise(gtsam, step)))
        m.records.append({"scan": k, "submap": target.index, "pose": None if res is None else res.pose,
                          "accepted": verdict, "edge": gated,
                          "covariance": None if res is None else res.calibrated_covariance})
        castable[k] = usable[k] and gated                 # else only once the graph has placed it
        if gated:
            m.accepted += 1
            est[k] = compose(est[target.key], res.pose)
            self._match_edge(gtsam, m.graph, target.key, k, res, self.options.front_end_inflation)
        else:
            est[k] = pred
        est[k, 2] = wrap_angle(est[k, 2])
        step = delta if edge is not None and edge[0] == k - 1 else compose(inverse(est[k - 1]), est[k])
        m.travelled[k] = m.travelled[k - 1] + math.hypot(step[0], step[1])
        m.values.insert(k, gtsam.Pose2(*est[k]))
        m.keys.append(k)
        for s in m.submaps:
            s.scans.append(k)
            if opts.submap_frames and not (gated and s is target):
                self._member_edge(gtsam, m.graph, s, k, est)
        if k % (opts.submap_scans // 2) == 0:
            self._open_submap(m, k)
        m.closed = len(m.submaps[0].scans) >= opts.submap_scans
        if m.closed:
            self._complete(m)

    def _complete(self, m):
        """The older open submap is complete: its loop closures, then an optimisation."""
        finished = m.submaps.pop(0)
        k = len(m.scans) - 1
        t0 = time.perf_counter()
        m.loops += self._close_loops(m.scans, finished, m.done, m.est, m.travelled, m.graph, m.gtsam, m.usable,
                                     [lp for lp in m.loops if lp["edge"]])
        m.done.append(finished)
        t1 = time.perf_counter()
        m.seconds["loop closing"] += t1 - t0
        m.est[m.keys] = m.solver.optimise(m.graph, m.values, m.est, m.keys)
        m.target_cast = None                              # cast again at the new estimates
        self._counts = {}
        m.castable[:k + 1] = m.usable[:k + 1]             # the graph has placed every scan so far
        m.values = pose_graph.values(m.gtsam, m.est, m.keys)
        m.seconds["optimisation"] += time.perf_counter() - t1

    def finish(self) -> SlamResult:
        """End the run of ``add``: the last submap's loop closures, a last optimisation, the
        ``audit``, the global map; the mapper is then ready for another run. Refused
        (InvalidOptionError, the run kept: more scans may come) without a scan, without one usable
        beam, or when every scan carries the same odometry pose (as ``run`` refuses such a log)."""
        self._check_unbroken()
        m = self._mapping
        if m is None or not m.scans:
            raise InvalidOptionError("no scan was added: nothing to map")
        n = len(m.scans)
        if not m.usable[:n].any():
            raise InvalidOptionError(NO_BEAM)
        if n > 1 and np.all(m.odo[:n] == m.odo[0]):
            raise InvalidOptionError(NO_ODOMETRY)
        try:
            return self._finish(m, n)
        finally:
            self.close()

    def _finish(self, m, n):
        gtsam, opts, seconds = m.gtsam, self.options, m.seconds
        if n > 1 and not m.closed:                        # the older open submap ends with the log
            self._complete(m)
        est = m.est
        t0 = time.perf_counter()
        m.optimise()
        t1 = time.perf_counter()
        seconds["optimisation"] += t1 - t0
        disagreements = None
        if opts.audit is not None:
            disagreements = self.audit(m.scans, m.done, est)
            if opts.audit == "repair":
                repairs = self._repair(m.scans, m.done, est, m.travelled, m.graph, gtsam, disagreements, m.loops)
                if repairs:
                    m.optimise()
            t0, t1 = t1, time.perf_counter()
            seconds["audit"] += t1 - t0
        if opts.loop_gate is not None and self._gate_loops(m):
            m.optimise()
            for pair in disagreements or ():          # the audit's pairs as the graph now joins them
                pair["gated"] = any(lp.get("gated") and lp["submaps"] == pair["submaps"] for lp in m.loops)
                pair["repaired"] = pair["repaired"] and any(
                    lp["edge"] and lp["repair"] and lp["submaps"] == pair["submaps"] for lp in m.loops)
        t0, t1 = t1, time.perf_counter()
        seconds["optimisation"] += t1 - t0
        world = scans_to_grid(m.scans, est[:n], resolution=opts.resolution, model=self._map_model)
        seconds["final map"] += time.perf_counter() - t1
        frame_keys = [sub.key for sub in sorted(m.done + m.submaps, key=lambda sub: sub.index)]
        parts = np.array(m.match_parts, dtype=np.float64).reshape(-1, 3)
        return SlamResult(poses=est[:n].copy(), timestamps=np.array([s.timestamp for s in m.scans], dtype=np.float64),
                          map=world, graph=m.graph, values=m.values, frames=est[frame_keys],
                          scan_matches=(m.accepted, m.tried), loops=m.loops, scans=m.records, seconds=seconds,
                          options=opts, match_seconds=parts.sum(axis=1), match_parts=parts, loops_tied=self._tied,
                          loops_few_walls=self._few,
                          disagreements=disagreements, add_seconds=np.array(m.add_seconds),
                          jump_checks=m.jump_checks)

    def _gate_loops(self, m) -> int:
        """Take out of the graph each loop closure whose residual at the optimised poses (``m.values``),
        squared in its own covariance, exceeds ``loop_gate`` (the Cauchy kernel had already all but
        silenced it), as does one whose chi-square is not a number: its record gets "residual" (that
        chi-square, as every closure in the graph does) and "edge" False, "gated" True. Returns how
        many."""
        taken = 0
        for loop in m.loops:
            if loop["edge"]:
                factor = m.graph.at(loop["factor"])
                loop["residual"] = factor.noiseModel().noise().squaredMahalanobisDistance(
                    factor.unwhitenedError(m.values))
                loop["gated"] = not bool(loop["residual"] <= self.options.loop_gate)
                if loop["gated"]:
                    m.graph.remove(loop["factor"])
                    loop["edge"] = False
                    taken += 1
        return taken

    def _open_submap(self, m, k):
        """A new submap from scan ``k`` on. With ``submap_frames`` its frame (graph key ``FRAME_KEY``
        + its index) starts at the scan's estimate, tied to it by a member edge; else its frame is
        the scan's own node."""
        index = len(m.done) + len(m.submaps)
        submap = _Submap(index, k, FRAME_KEY + index if self.options.submap_frames else k)
        submap.scans.append(k)
        if self.options.submap_frames:
            m.est[submap.key] = m.est[k]
            m.travelled[submap.key] = m.travelled[k]
            m.values.insert(submap.key, m.gtsam.Pose2(*m.est[k]))
            m.keys.append(submap.key)
            self._member_edge(m.gtsam, m.graph, submap, k, m.est)
        m.submaps.append(submap)

    def _cast_final(self, scans, submap, est):
        """Cast a complete submap (all its scans) at the current estimates, for loop closures."""
        submap.final_grid, submap.final_poses = self._cast_submap(scans, submap, est)
        submap.footprint = Footprint(submap.final_grid)

    def _few_walls(self, a, b, guess) -> bool:
        """Whether fewer than ``LOOP_MIN_WALLS`` walls of complete submaps ``a`` and ``b`` land on each
        other's known cells at ``guess`` (r_a2b; the verdict's count, ``_verdict.compare_walls``)."""
        wa = self._matcher.prepare(a.final_grid, levels=1).wall_distance
        wb = self._matcher.prepare(b.final_grid, levels=1).wall_distance
        return compare_walls(wa, wb, placed_walls(wa, wb, guess))[0] < LOOP_MIN_WALLS

    def _moved_since_cast(self, submap, est) -> bool:
        """Whether the graph has moved one of a complete submap's scans, in its frame, by more than
        ``RECAST_CELLS`` along x or y or ``RECAST_RAD`` since its last cast."""
        scans, cast = submap.final_poses
        now = compose(inverse(est[submap.key]), est[np.array(scans, dtype=np.int64)]).reshape(-1, 3)
        return bool(np.abs(now[:, :2] - cast[:, :2]).max() > RECAST_CELLS * self.options.resolution
                    or np.abs(wrap_angle(now[:, 2] - cast[:, 2])).max() > RECAST_RAD)

    def _neighbour_votes(self, loop, edges, est, travelled):
        """(agree, disagree): how many loop closures already in the graph with both frames within
        ``NEIGHBOUR_PATH`` metres of travel of this one's predict its relative pose within 3 sd,
        through the current estimates' short chains between the frames (their uncertainty from
        the odometry model: conservative, the estimates are better)."""
        per_m, _, rad_per_m, floor_m, floor_rad = self.options.odometry_sd
        a, b = loop["frames"]
        z = loop["pose"]
        t_z, r_z = _sd(loop["covariance"])
        agree = disagree = 0
        if not edges:
            return agree, disagree
        # the travel to every closure's frames at once (a lookup per closure was most of fhw's
        # loop closing in Python: 430 closures in its graph); the same floats as one by one
        frames = np.array([other["frames"] for other in edges], dtype=np.int64)
        along = np.abs(travelled[frames.ravel()].reshape(-1, 2) - np.array([travelled[a], travelled[b]]))
        near = np.flatnonzero(along.max(axis=1) <= NEIGHBOUR_PATH)
        if len(near) == 0:
            return agree, disagree
        # all the neighbours at once (one by one, fhw's 430 votes were a fifth of its loop closing)
        frames, path = frames[near], along[near].sum(axis=1)
        poses = np.array([edges[i]["pose"] for i in near], dtype=np.float64)
        t_o, r_o = _sd([edges[i]["covariance"] for i in near])
        predicted = compose(compose(compose(inverse(est[a]), est[frames[:, 0]]), poses),
                            compose(inverse(est[frames[:, 1]]), est[b]))
        error = compose(inverse(z), predicted)
        sd_r = np.sqrt(r_z**2 + r_o**2 + (rad_per_m * path + floor_rad) ** 2)
        sd_t = np.sqrt(t_z**2 + t_o**2 + (per_m * path + floor_m) ** 2 + (math.hypot(z[0], z[1]) * sd_r) ** 2)
        agrees = (np.hypot(error[:, 0], error[:, 1]) <= 3.0 * sd_t) & (np.abs(wrap_angle(error[:, 2])) <= 3.0 * sd_r)
        agree = int(np.count_nonzero(agrees))
        return agree, len(near) - agree

    def _admitted(self, loop, edges, est, travelled) -> bool:
        """Whether an accepted loop closure enters the graph: unless the neighbours' vote
        (``loop_consistency``) is against it. Sets its "edge" (and "votes"); appends it to
        ``edges`` when it enters."""
        if loop["accepted"] and self.options.loop_consistency:
            agree, disagree = self._neighbour_votes(loop, edges, est, travelled)
            loop["votes"] = (agree, disagree)
            loop["edge"] = disagree <= agree
        if loop["edge"]:
            edges.append(loop)
        return loop["edge"]

    def _close_loops(self, scans, submap, done, est, travelled, graph, gtsam, usable, edges):
        opts = self.options
        out = []
        if not usable[submap.scans].any():
            return out                                   # final_grid stays None: never matched
        self._cast_final(scans, submap, est)
        shared = set(submap.scans)
        candidates = []                                  # (other, guess, window)
        for other in done:
            if other.final_grid is None or shared.intersection(other.scans):
                continue
            a, b = other.key, submap.key
            drift = opts.loop_growth * abs(travelled[b] - travelled[a])
            reach = opts.loop_radius + drift
            if math.hypot(*(est[b, :2] - est[a, :2])) > reach:
                continue
            guess = compose(inverse(est[a]), est[b])
            if overlap_share(other.footprint, submap.footprint, guess) < LOOP_MIN_OVERLAP:
                continue
            if opts.loop_ties is None and self._moved_since_cast(other, est):
                self._cast_final(scans, other, est)         # now: a helper may take it
            window = None
            if opts.loop_search is not None and drift > opts.loop_search:
                window = (min(drift, LOOP_SEARCH_MAX), min(drift, LOOP_SEARCH_MAX) / LOOP_SEARCH_ARM)
            elif self._few_walls(other, submap, guess):
                self._few += 1
                continue
            candidates.append((other, guess, window))
        results, helped = (None, set()) if opts.loop_ties is not None else self._match_candidates(submap, candidates)
        apart, matched = None, 0                         # loop_ties: tie_distances to the candidates
        for index, (other, guess, window) in enumerate(candidates):
            a, b = other.key, submap.key
            if results is not None:
                res = results[index]
            else:
                if apart is None and matched >= LOOP_TIE_FREE:
                    apart = tie_distances(b, [c[0].key for c in candidates], edges, travelled)
                if matched >= LOOP_TIE_FREE and apart[index] <= opts.loop_ties:
                    self._tied += 1
                    continue
                if self._moved_since_cast(other, est):
                    self._cast_final(scans, other, est)
                res = self._matcher.match(other.final_grid, submap.final_grid, guess, search_window=window)
                matched += 1
            loop = _loop_record(other, submap, guess, window, res, helper=index in helped, repair=False)
            out.append(loop)
            if self._admitted(loop, edges, est, travelled):
                apart = None
                loop["factor"] = self._match_edge(gtsam, graph, a, b, res)
        return out

    def audit(self, scans, submaps, est) -> list:
        """The pairs of ``submaps`` (complete) that share no scan and disagree at the estimates
        ``est`` (see ``DISAGREE_CONFLICT``): each as cast at ``est`` in its frame (again when the
        estimates moved a scan in it, ``_moved_since_cast``) and its walls
        placed on the other's cells (``_verdict.compare_walls``, both ways), for the pairs whose
        boxes in the world meet. Negative information as a self-check: a run that mapped one place
        twice, shifted, has walls of one visit on the other's free space."""
        self._counts = {}
        usable = [sub for sub in submaps if sub.final_grid is not None]
        for sub in usable:
            if self._moved_since_cast(sub, est):
                self._cast_final(scans, sub, est)
        # the finest level only (the coarser ones were 40 % of the preparation; a repair's match
        # makes them when it needs them)
        walls = {sub.index: self._matcher.prepare(sub.final_grid, levels=1).wall_distance for sub in usable}
        # each submap's box in the world: pairs whose boxes do not meet share no cell
        boxes = np.array([footprint_bounds(sub.final_grid, est[sub.key], 0.0, 0.0) for sub in usable]).reshape(-1, 4)
        pairs, placed = [], {sub.index: [] for sub in usable}     # submap -> the walls placed on its grid
        for j, b in enumerate(usable):
            for i, a in enumerate(usable[:j]):
                if (set(a.scans).intersection(b.scans) or boxes[i, 0] > boxes[j, 2] or boxes[j, 0] > boxes[i, 2]
                        or boxes[i, 1] > boxes[j, 3] or boxes[j, 1] > boxes[i, 3]):
                    continue
                pose = compose(inverse(est[a.key]), est[b.key])
                b_in_a, a_in_b = placed_walls(walls[a.index], walls[b.index], pose)
                placed[a.index].append(b_in_a)
                placed[b.index].append(a_in_b)
                pairs.append((a.index, b.index))
        # each grid's lookups at once (one by one they were a third of fhw's audit): the same
        # distances, handed back to the pairs in the order they were placed
        found = {}
        for index, points in placed.items():
            if points:
                d = walls[index].lookup(np.concatenate([p[0] for p in points]), np.concatenate([p[1] for p in points]))
                found[index] = iter(np.split(d, np.cumsum([len(p[0]) for p in points])[:-1]))
        out = []
        for a, b in pairs:
            compared, agreement, conflict = wall_statistics(np.concatenate([next(found[a]), next(found[b])]))
            if compared >= MIN_WALLS and agreement < DISAGREE_AGREEMENT and conflict > DISAGREE_CONFLICT:
                out.append({"submaps": (a, b), "walls": compared, "agreement": agreement,
                            "conflict": conflict, "repaired": False})
        return out

    def _repair(self, scans, submaps, est, travelled, graph, gtsam, disagreements, loops) -> int:
        """Match each disagreeing pair that no loop closure in the graph joins after a search around
        the graph's relative pose (``audit``): each match goes into ``loops``, the accepted ones
        that pass the neighbours' vote (``loop_consistency``) into the graph. Returns how many."""
        edges = [loop for loop in loops if loop["edge"]]
        joined = {loop["submaps"] for loop in edges}
        by_index = {sub.index: sub for sub in submaps}
        added = 0
        for pair in disagreements:
            pair["joined"] = pair["submaps"] in joined
            if pair["joined"]:
                continue
            a, b = (by_index[i] for i in pair["submaps"])
            guess = compose(inverse(est[a.key]), est[b.key])
            reach = min(max(0.5, self.options.loop_growth * abs(travelled[b.key] - travelled[a.key])), LOOP_SEARCH_MAX)
            window = (reach, reach / LOOP_SEARCH_ARM)
            res = self._matcher.match(a.final_grid, b.final_grid, guess, search_window=window)
            loop = _loop_record(a, b, guess, window, res, helper=False, repair=True)
            loops.append(loop)
            if self._admitted(loop, edges, est, travelled):
                pair["repaired"] = True
                added += 1
                loop["factor"] = self._match_edge(gtsam, graph, a.key, b.key, res)
        return added

    def _match_candidates(self, submap, candidates):
        """Each candidate's match of the new submap in the older one, in order, and the indices of
        those a helper matched: the helpers (``workers``) take candidates from the end (first those
        whose older submap they hold as cast) while this process matches from the front, each as
        soon as it is free; the same results as matching them all here, bit for bit (``_helper``)."""
        results, helped = [None] * len(candidates), set()
        pending = list(range(len(candidates)))
        out = {}                                          # helper -> the candidate it matches

        def collected(wait):
            for helper in list(out):
                done = helper.collect(wait)
                if done is not None or not helper.alive or helper.task is None:
                    index = out.pop(helper)
                    if done is not None:
                        results[index] = done[1]
                        helped.add(index)
                    else:                                 # it failed: matched here instead
                        pending.insert(0, index)

        while pending or out:
            collected(False)
            for helper in self._helpers:
                # a helper only while this process has another to match (else it would wait for the
                # helper's preparing of maps it has not seen), the last one whose older submap it holds
                if len(pending) >= 2 and helper not in out and helper.idle:
                    held = [i for i in pending[1:] if helper.holds(candidates[i][0].final_grid)]
                    index = held[-1] if held else pending[-1]
                    other, guess, window = candidates[index]
                    if helper.give(index, ((other.index, other.final_grid), (submap.index, submap.final_grid)),
                                   guess, window):
                        pending.remove(index)
                        out[helper] = index
            if pending:
                index = pending.pop(0)
                other, guess, window = candidates[index]
                results[index] = self._matcher.match(other.final_grid, submap.final_grid, guess, search_window=window)
            elif out:
                collected(True)
        return results, helped


def _same_place(a, b, metres: float = 0.2, radians: float = 0.1) -> bool:
    """Whether two poses lie within ``metres`` and ``radians`` of each other."""
    return bool(math.hypot(a[0] - b[0], a[1] - b[1]) <= metres and abs(wrap_angle(a[2] - b[2])) <= radians)


def _loop_record(a: _Submap, b: _Submap, guess, window, res, *, helper: bool, repair: bool) -> dict:
    """The record of a loop-closure match of submap ``b`` in ``a`` (``SlamResult.loops``); its
    "edge" starts as the verdict's."""
    return {"helper": helper, "window": window, "hypotheses": res.hypotheses, "submaps": (a.index, b.index),
            "frames": (a.key, b.key), "anchors": (a.anchor, b.anchor), "members": (a.final_poses, b.final_poses),
            "accepted": res.accepted, "pose": res.pose, "guess": guess, "covariance": res.calibrated_covariance,
            "evidence": res.evidence, "status": res.status.name, "edge": res.accepted, "repair": repair}


def tie_distances(source, targets, edges, travelled) -> np.ndarray:
    """Metres of travel from frame ``source`` to each frame of ``targets`` (keys) along the
    trajectory and across the loop closures in ``edges`` (crossing one costs nothing): how far
    apart the graph's closures leave two frames (``loop_ties``). The trajectory between two frames
    is a chain of the frames between them in travel order."""
    ends = np.array([e["frames"] for e in edges], dtype=np.int64).reshape(-1, 2)
    keys = np.concatenate([[source], np.asarray(targets, dtype=np.int64), ends.ravel()])
    t = travelled[keys]
    order = np.argsort(t, kind="stable")
    first = 1 + len(targets) + 2 * np.arange(len(ends))                  # each closure's first end
    # along the trajectory between neighbours in travel order, across each closure; every weight
    # raised by a femtometre so that a zero (two frames at one place) stays an edge
    rows = np.concatenate([order[:-1], first])
    cols = np.concatenate([order[1:], first + 1])
    weights = np.concatenate([np.diff(t[order]), np.zeros(len(ends))]) + 1e-15
    lightest = np.argsort(weights, kind="stable")                         # of two edges between a pair
    pairs = np.sort(np.column_stack([rows, cols])[lightest], axis=1)
    pairs, index = np.unique(pairs, axis=0, return_index=True)            # the lightest is first
    # SciPy's sparse graphs are imported where used (0.1-0.2 s a process, and only loop_ties uses them)
    from scipy import sparse
    from scipy.sparse import csgraph

    graph = sparse.csr_matrix((weights[lightest][index], (pairs[:, 0], pairs[:, 1])), shape=(len(keys), len(keys)))
    return csgraph.dijkstra(graph, directed=False, indices=0)[1:1 + len(targets)]


def footprint_bounds(grid, pose, metres: float = CROP_METRES, radians: float = CROP_RADIANS):
    """(x_min, y_min, x_max, y_max): the box that ``grid`` covers when placed at ``pose`` (its
    frame in the other's), widened by ``metres`` plus ``radians`` times the distance of its
    farthest corner from its frame's origin."""
    x0, x1, y0, y1 = grid.extent
    corners = np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]])
    placed = transform_points(pose, corners)
    margin = metres + radians * float(np.hypot(corners[:, 0], corners[:, 1]).max())
    return (*(placed.min(axis=0) - margin), *(placed.max(axis=0) + margin))


class Footprint:
    """A map's known cells as ``overlap_share`` reads them, computed once per map: its known mask
    and the centres of every ``stride``-th known cell (row-major)."""

    def __init__(self, grid, stride: int = 5):
        self.grid = grid
        self.known = grid.known
        rows, cols = cells(self.known)
        self.samples = grid.cell_centres(rows[::stride], cols[::stride])


def overlap_share(a: Footprint, b: Footprint, pose) -> float:
    """The share of ``b``'s sampled known cells whose centres land on known cells of ``a`` when
    ``b`` is placed at ``pose`` (r_A2B); 0 when ``b`` knows none."""
    if len(b.samples) == 0:
        return 0.0
    ra, ca = a.grid.cell_of(transform_points(pose, b.samples))
    inside = (ra >= 0) & (ca >= 0) & (ra < a.known.shape[0]) & (ca < a.known.shape[1])
    hit = np.zeros(len(b.samples), dtype=bool)
    hit[inside] = a.known[ra[inside].astype(np.intp), ca[inside].astype(np.intp)]
    return float(hit.mean())


def _sd(covariance):
    """(largest translation sd, rotation sd) of an (x, y, theta) covariance, or of each of a batch
    (..., 3, 3) of them."""
    c = np.asarray(covariance, dtype=np.float64)
    translation = np.sqrt(np.maximum(np.linalg.eigvalsh(c[..., :2, :2]).max(axis=-1), 0.0))
    rotation = np.sqrt(np.maximum(c[..., 2, 2], 0.0))
    return (float(translation), float(rotation)) if c.ndim == 2 else (translation, rotation)


def slam(log: LaserLog, options: SlamOptions = None, **overrides) -> SlamResult:
    """``Slam(options, **overrides).run(log)``."""
    return Slam(options, **overrides).run(log)
