"""The mapping loop (issue 12): a simulated run against its exact truth, the outputs, bad input,
and the trajectory metrics against evo."""

import dataclasses
import math
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from taichi_match import InvalidOptionError, LogFormatError, Matcher, compose, inverse, transform_points, wrap_angle
from taichi_match.cli import main
from taichi_match.evaluation import frame_reference, trajectory_errors
from taichi_match.logs import LaserLog, read_carmen, read_tum, write_carmen
from taichi_match.simulate import cast_scan, floor_plan, simulate_log

gtsam = pytest.importorskip("gtsam")

from taichi_match.slam import FRAME_KEY, Slam, SlamOptions, write_outputs  # noqa: E402  (needs gtsam)


@pytest.fixture(scope="module")
def simulated():
    return simulate_log(0)


@pytest.fixture(scope="module")
def mapped(simulated):
    return Slam().run(simulated.log)


@pytest.fixture(scope="module")
def short_run():
    return simulate_log(1, laps=0.4)


def _node_truth(loop, truth):
    """The exact poses of the two nodes a loop closure joins: a scan's own; a submap's frame (a
    node of its own, ``submap_frames``) the motion that carries its scans' cast poses onto their truth."""
    return [truth[key] if key < len(truth) else frame_reference(*members, truth)
            for key, members in zip(loop["frames"], loop["members"])]


def test_frame_reference_recovers_a_known_frame():
    """Scans placed in a known frame F (their poses in it: F^-1 composed with their truth) give F
    back, to rounding, also with the angles wrapped around +-pi; and a mean where the scans
    disagree (an oracle by hand: two scans whose frames differ by a translation only)."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        truth = np.column_stack([rng.uniform(-20, 20, (30, 2)), rng.uniform(-np.pi, np.pi, 30)])
        frame = np.array([*rng.uniform(-20, 20, 2), rng.uniform(-np.pi, np.pi)])
        scans = rng.choice(30, 8, replace=False)
        in_frame = np.array([compose(inverse(frame), truth[j]) for j in scans])
        got = frame_reference(scans, in_frame, truth)
        np.testing.assert_allclose(got[:2], frame[:2], atol=1e-9)
        assert abs(wrap_angle(got[2] - frame[2])) < 1e-12
    truth = np.array([[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    np.testing.assert_allclose(frame_reference([0, 1], [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], truth), [1.5, 0.0, 0.0])


def test_simulated_run_recovers_the_truth(simulated, mapped):
    """Twice round a simulated building with drifting odometry: every scan gets a pose, the
    trajectory is within the issue's ATE targets of the exact truth and 10 times better than the
    odometry, and loop closures were found."""
    assert mapped.poses.shape == (len(simulated.log), 3) and np.all(np.isfinite(mapped.poses))
    errors = trajectory_errors(mapped.poses, simulated.truth)
    odometry = trajectory_errors(simulated.log.poses, simulated.truth)
    assert errors["ate_m"] <= 0.10 and errors["ate_deg"] <= 1.0, errors
    assert errors["ate_m"] * 10 <= odometry["ate_m"], (errors, odometry)
    assert sum(loop["accepted"] for loop in mapped.loops) >= 5


def test_simulated_run_relative_translation_error_within_target(simulated, mapped):
    """The issue's RPE target in metres on this run: 1.3 cm (1.5 with a submap's frame at its first
    scan's node; 2.9 cm at the start of the session that made walls on unknown cells next to the
    other map's walls pay their distance); runs with
    the odometry moved by a micrometre give 1.2-1.4 cm (bench/SLAM.md's spread table, 2026-12-06;
    1.4-1.6 with a submap's frame at its first scan's node)."""
    errors = trajectory_errors(mapped.poses, simulated.truth)
    assert errors["rpe_m"] <= 0.03, errors


def test_simulated_run_relative_rotation_error_within_target(simulated, mapped):
    """The issue's RPE target in degrees on this run: 0.23 (0.19-0.24 over twenty runs with the
    odometry moved by a micrometre, bench/SLAM.md; 0.22 and 0.19-0.26 before ``turn_edge``). Not
    met reliably before each submap had a frame node of its own: with its frame at its first
    scan's node 0.20-0.35 (median 0.23, bench/SLAM_before_submap_frames.md), earlier 0.20-0.58
    (scans at the 90-degree turns slid 0.3-0.6 degree for several scans in a row: docs/slam.md)."""
    errors = trajectory_errors(mapped.poses, simulated.truth)
    assert errors["rpe_deg"] <= 0.3, errors


def test_simulated_run_loop_closures_against_the_truth(simulated, mapped):
    """The loop closures in the graph against the exact truth of the two nodes each joins (a submap
    frame's: ``evaluation.frame_reference``; wrong: 0.2 m or 1 degree off, Cartographer's
    criterion): 3 of 133 on this run (3 of 136 before ``turn_edge``), 8 of 141 before
    ``loop_gate`` (5-10 over twenty runs with the odometry moved by a micrometre, bench/SLAM.md
    before the gate; 8-16 with a submap's frame at its first scan's node,
    bench/SLAM_before_submap_frames.md). Pins this run's spread; the target (none wrong) is not met."""
    from taichi_match import compose, inverse, wrap_angle

    truth = simulated.truth
    edges = [loop for loop in mapped.loops if loop["edge"]]
    errors = [compose(inverse(compose(inverse(a), b)), loop["pose"])
              for loop in edges for a, b in [_node_truth(loop, truth)]]
    wrong = [e for e in errors if math.hypot(e[0], e[1]) > 0.2 or abs(math.degrees(wrap_angle(e[2]))) > 1.0]
    assert len(edges) >= 100 and len(wrong) <= 5, (len(wrong), len(edges))


def _se2_log(pose):
    """SE(2)'s logarithm of (x, y, theta) in plain NumPy: (v_x, v_y, theta), the translation
    taken through the inverse of V(theta) (an independent check of gtsam's ``Pose2.Logmap``)."""
    x, y, w = pose
    if abs(w) < 1e-12:
        return np.array([x, y, w])
    a, b = math.sin(w) / w, (1.0 - math.cos(w)) / w
    return np.append(np.linalg.solve(np.array([[a, -b], [b, a]]), [x, y]), w)


def _factor_set(graph):
    """The graph's between-factors as (keys, measured x, y, theta to 1e-9: gtsam keeps the angle as
    its cosine and sine)."""
    out = set()
    for i in range(graph.size()):
        factor = graph.at(i)
        if isinstance(factor, gtsam.BetweenFactorPose2):
            m = factor.measured()
            out.add((tuple(factor.keys()), *np.round([m.x(), m.y(), m.theta()], 9)))
    return out


def _loop_key(loop):
    return (tuple(loop["frames"]), *np.round(loop["pose"], 9))


def test_loop_gate_takes_out_the_closures_the_optimised_graph_contradicts(simulated, mapped, monkeypatch):
    """Every loop closure in the graph at the end has its residual at the optimised poses (those
    the gate sees, before the graph is optimised without the closures it takes out), squared in
    its own covariance, recomputed here from the frames' poses in NumPy (SE(2)'s logarithm, the
    covariance turned into the relative pose's axes): those above ``loop_gate`` are out of the
    graph, the others in it. On this run the gate takes out some, most of them wrong against the
    exact truth, and leaves at most 5 wrong ones in the graph (8 without it)."""
    seen = []
    original = Slam._gate_loops

    def watched(self, m):
        seen.append(gtsam.Values(m.values))
        return original(self, m)

    monkeypatch.setattr(Slam, "_gate_loops", watched)
    result = Slam().run(simulated.log)
    np.testing.assert_array_equal(result.poses, mapped.poses)
    (values,) = seen
    gate = result.options.loop_gate
    present = _factor_set(result.graph)
    checked = [loop for loop in result.loops if "residual" in loop]
    assert len(checked) >= 100
    for loop in checked:
        a, b = (values.atPose2(key) for key in loop["frames"])
        estimate = compose(inverse([a.x(), a.y(), a.theta()]), [b.x(), b.y(), b.theta()])
        error = _se2_log(compose(inverse(loop["pose"]), estimate))
        c, s = math.cos(loop["pose"][2]), math.sin(loop["pose"][2])
        turn = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        chi2 = error @ np.linalg.solve(turn @ np.asarray(loop["covariance"]) @ turn.T, error)
        assert loop["residual"] == pytest.approx(chi2, rel=1e-6, abs=1e-9)
        assert loop["gated"] == (chi2 > gate) and loop["edge"] == (chi2 <= gate)
        assert (_loop_key(loop) in present) == loop["edge"]
    truth = simulated.truth

    def wrong(loop):
        fa, fb = _node_truth(loop, truth)
        e = compose(inverse(compose(inverse(fa), fb)), loop["pose"])
        return math.hypot(e[0], e[1]) > 0.2 or abs(math.degrees(wrap_angle(e[2]))) > 1.0

    gated = [loop for loop in checked if loop["gated"]]
    assert gated and 2 * sum(map(wrong, gated)) > len(gated), [wrong(loop) for loop in gated]
    assert sum(wrong(loop) for loop in checked if loop["edge"]) <= 5


def test_loop_gate_takes_out_a_planted_false_closure(one_lap, monkeypatch):
    """The first accepted loop closure moved by 0.6 m and 3 degrees, its covariance kept, and let in
    (no neighbours' vote, no audit): the gate takes it out of the graph (``graph.g2o``'s readers
    have no robust kernel); without the gate it stays in. The poses differ by under a centimetre:
    the Cauchy kernel had already all but silenced it, and the gate acts only at the end."""
    original = Matcher.match
    planted = []

    def lying(self, a, b, guess, *args, **kwargs):
        res = original(self, a, b, guess, *args, **kwargs)
        if res.accepted and not planted and self is not mapper._scan_matcher:
            res = dataclasses.replace(res, pose=compose(res.pose, [0.6, 0.0, math.radians(3.0)]))
            planted.append(res.pose)
        return res

    monkeypatch.setattr(Matcher, "match", lying)
    poses = {}
    for gate in (SlamOptions().loop_gate, None):
        planted.clear()
        mapper = Slam(loop_gate=gate, loop_consistency=False, audit=None)
        result = mapper.run(one_lap)
        (lie,) = [loop for loop in result.loops if np.array_equal(loop["pose"], planted[0])]
        assert (_loop_key(lie) in _factor_set(result.graph)) == lie["edge"] == (gate is None)
        assert lie.get("gated", False) == (gate is not None)
        if gate is not None:
            assert lie["residual"] > 10 * gate
        poses[gate] = result.poses
    moved = np.abs(poses[None][:, :2] - poses[SlamOptions().loop_gate][:, :2]).max()
    assert 0 < moved < 0.01, moved


def test_loop_gate_takes_out_a_closure_whose_residual_is_not_a_number():
    """A loop closure whose chi-square gtsam gives as NaN (a covariance of 1e20 along one direction:
    the red-team pass that found a NaN passing the gate) leaves the graph; a closure beside it
    with a finite, small chi-square stays. The gate alone, on a graph made here: a whole run
    meets such a NaN only for some bits of its poses."""
    import types

    c, s = math.cos(0.7), math.sin(0.7)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(0.0, 0.0, 0.0), gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
    for key, pose in ((0, (0.0, 0.0, 0.0)), (1, (0.01, 0.0, 0.0))):
        values.insert(key, gtsam.Pose2(*pose))
    covariances = (turn @ np.diag([1e20, 1e-4, 1e-6]) @ turn.T, np.diag([1e-2, 1e-2, 1e-3]))
    mapper = Slam()
    for covariance in covariances:                                    # as the loop's closures: robust
        graph.add(gtsam.BetweenFactorPose2(0, 1, gtsam.Pose2(0.0, 0.0, 0.0), mapper._robust_noise(gtsam, covariance)))
    chi2 = [graph.at(i).noiseModel().noise().squaredMahalanobisDistance(graph.at(i).unwhitenedError(values))
            for i in (1, 2)]
    assert math.isnan(chi2[0]) and chi2[1] < 1.0, chi2                 # what the test is about
    loops = [{"edge": True, "factor": 1}, {"edge": True, "factor": 2}]
    mapping = types.SimpleNamespace(loops=loops, graph=graph, values=values)
    assert mapper._gate_loops(mapping) == 1
    assert loops[0]["gated"] is True and not loops[0]["edge"] and math.isnan(loops[0]["residual"])
    assert loops[1]["gated"] is False and loops[1]["edge"] and loops[1]["residual"] == chi2[1]
    assert graph.at(1) is None and graph.at(2) is not None


def test_turn_edge_charges_the_grid_edge_after_sharp_turns_only(short_run, monkeypatch):
    """The front end's match of a scan whose odometry step turned more than ``turn_edge`` charges
    walls off the grid (``grid_edge="unknown"``), every other match leaves the default: each
    front-end call's overrides against the step's turn, computed here from the log's poses."""
    calls = []
    original = Matcher.match

    def spy(self, a, b, guess, *args, **kwargs):
        if self is mapper._scan_matcher and "search_window" not in kwargs:
            calls.append(kwargs.get("grid_edge"))
        return original(self, a, b, guess, *args, **kwargs)

    monkeypatch.setattr(Matcher, "match", spy)
    poses = short_run.log.poses
    turns = np.abs([wrap_angle(compose(inverse(p), q)[2]) for p, q in zip(poses[:-1], poses[1:])])
    for limit in (math.radians(60.0), 0.3, None):
        calls.clear()
        mapper = Slam(turn_edge=limit)
        mapper.run(short_run.log)
        assert len(calls) == len(turns)
        want = ["unknown" if limit is not None and turn > limit else None for turn in turns]
        assert calls == want
        assert limit != 0.3 or "unknown" in want and None in want


def test_front_end_steps_after_right_angle_turns_against_the_truth():
    """Seed 2's world: each front-end match's step from the scan before (the estimates as they were
    then) against the truth's step. Default options: every step within 1 degree (the largest 0.84);
    with ``turn_edge`` None, scan 150 after a 91.5-degree turn turned 5.3 degrees too far and 50
    3.8 (the scan's box edge pulling: docs/slam.md, "2026-12-07, late")."""
    run = simulate_log(2)
    truth = np.asarray(run.truth)
    steps = {}

    class Watched(Slam):
        def _step(self, m, k):
            super()._step(m, k)
            steps[k] = compose(inverse(m.est[k - 1]), m.est[k])

    Watched().run(run.log)
    errors = [abs(math.degrees(wrap_angle(step[2] - compose(inverse(truth[k - 1]), truth[k])[2])))
              for k, step in steps.items()]
    assert len(errors) == len(truth) - 1 and max(errors) < 1.0, max(errors)


@pytest.mark.parametrize("value", [-0.1, 3.5, math.nan, True, "1"])
def test_turn_edge_refuses_anything_but_radians_in_0_pi(value):
    with pytest.raises(InvalidOptionError, match="turn_edge"):
        SlamOptions(turn_edge=value)


def test_loop_closures_see_older_submaps_as_the_graph_places_them(simulated, monkeypatch):
    """Every loop-closure match sees the older submap cast at poses (in its frame) within half a
    cell and 0.2 degree of the estimates of the moment; the graph does move some after their
    first cast, so some are cast again. The estimates are read from the live array the loop
    closing receives, the cast poses from each loop's record."""
    from taichi_match import compose, inverse, wrap_angle
    from taichi_match.slam import RECAST_CELLS, RECAST_RAD

    checked, recast, first_cast = [], set(), {}
    original = Slam._close_loops

    def checking(self, log, submap, done, est, *args):
        loops = original(self, log, submap, done, est, *args)
        for loop in loops:
            scans, cast = loop["members"][0]
            frame = loop["frames"][0]
            now = np.array([compose(inverse(est[frame]), est[j]) for j in scans])
            checked.append(max(np.abs(now[:, :2] - cast[:, :2]).max() / (RECAST_CELLS * self.options.resolution),
                               np.abs(wrap_angle(now[:, 2] - cast[:, 2])).max() / RECAST_RAD))
            first = first_cast.setdefault(loop["submaps"][0], cast)
            if not np.array_equal(first, cast):
                recast.add(loop["submaps"][0])
        return loops

    monkeypatch.setattr(Slam, "_close_loops", checking)
    Slam().run(simulated.log)
    assert len(checked) >= 100 and max(checked) <= 1.0, max(checked)
    assert recast, "no submap was cast again"


def test_simulated_run_with_submap_frames_off_meets_the_trajectory_targets(simulated):
    """With each submap's frame its first scan's node (``submap_frames=False``, the default before
    2026-12-06) the simulated run still meets the trajectory targets (bench/SLAM_before_submap_frames.md)."""
    errors = trajectory_errors(Slam(submap_frames=False).run(simulated.log).poses, simulated.truth)
    assert errors["ate_m"] <= 0.10 and errors["ate_deg"] <= 1.0, errors
    assert errors["rpe_m"] <= 0.03 and errors["rpe_deg"] <= 0.3, errors


def test_the_audit_finds_a_lap_mapped_out_of_place(simulated, monkeypatch):
    """The audit's self-check against a known fault: the final optimisation's answer with the
    second lap moved 0.8 m sideways of the simulated truth's map gives submaps of the two laps
    that disagree (walls of one on the other's free space), every pair across the fault; as
    optimised, none. Without ``audit`` no check is made."""
    import taichi_match._pose_graph as pose_graph
    import taichi_match.slam as slam_module

    optimise = pose_graph.optimise
    half = len(simulated.log) // 2
    first_of, scans = SlamOptions().submap_scans // 2, SlamOptions().submap_scans

    def shifted(gtsam, graph, values, keys):
        poses = optimise(gtsam, graph, values, keys)
        keys = np.asarray(keys)               # a submap frame moves with its first scan
        first_scan = np.where(keys >= slam_module.FRAME_KEY, (keys - slam_module.FRAME_KEY) * first_of, keys)
        poses[first_scan >= half, 1] += 0.8
        return poses

    found = Slam(audit="report").run(simulated.log)
    assert found.disagreements == [] and found.seconds["audit"] > 0
    monkeypatch.setattr(pose_graph, "optimise", shifted)            # each submap's and the end's
    broken = Slam(audit="report", loop_gate=None).run(simulated.log)
    pairs = broken.disagreements
    assert len(pairs) >= 5
    assert all(a * first_of < half <= b * first_of + scans for a, b in (p["submaps"] for p in pairs))
    assert all(p["agreement"] < 0.25 and p["conflict"] > 0.5 and not p["repaired"] for p in pairs)
    assert "pairs of submaps disagree" in slam_module.report(broken)
    assert Slam(audit=None).run(simulated.log).disagreements is None
    # "repair" searches each pair from the faulty relative pose: the closures it accepts undo the
    # fault, each moving its pair about 0.8 m (in the older frame) and turning it by about nothing,
    # onto the truth's relative pose of the two frames where the two submaps share many walls
    # (2026-12-06, submap frames: submaps 0 and 1 against 20 and 1 against 21, 551-789 walls
    # compared, within 5 mm and 0.1 degree of the frames' truth). Pairs that share less are
    # accepted farther off: 13 against 20 (103 walls) 0.20 m, 13 against 30 (200 walls) 0.10 m and
    # 0.45 degree (a known limit of thin closures: of the real logs' closures with 100-300 walls
    # compared 18-22 % are wrong against the references, docs/slam.md): of those only that they
    # move the pair most of the way is asserted.
    # (no ``loop_gate``: the faked optimum contradicts every closure across the fault, which the
    # gate would take out after the repair)
    repaired = Slam(audit="repair", loop_gate=None).run(simulated.log)
    closures = [lp for lp in repaired.loops if lp.get("repair") and lp["accepted"]]
    assert closures and sum(p["repaired"] for p in repaired.disagreements) == len(closures)
    well_supported = 0
    for loop in closures:
        moved = np.asarray(loop["pose"]) - np.asarray(loop["guess"])
        assert abs(math.hypot(moved[0], moved[1]) - 0.8) < 0.25 and abs(moved[2]) < math.radians(1.5), moved
        if loop["evidence"].walls_compared < 300:            # six times the verdict's minimum
            continue
        well_supported += 1
        a, b = _node_truth(loop, simulated.truth)
        off = np.asarray(loop["pose"]) - compose(inverse(a), b)
        assert abs(math.hypot(moved[0], moved[1]) - 0.8) < 0.05, moved
        assert math.hypot(off[0], off[1]) < 0.05 and abs(wrap_angle(off[2])) < math.radians(0.25), off
    assert well_supported >= 2
    # pairs a loop closure in the graph joins already are not searched again, and said so
    joined = [p for p in repaired.disagreements if p["joined"]]
    in_graph = {lp["submaps"] for lp in repaired.loops if lp["edge"] and not lp["repair"]}
    assert {p["submaps"] for p in joined} == {p["submaps"] for p in repaired.disagreements} & in_graph
    assert joined and not any(p["repaired"] for p in joined)
    text = slam_module.report(repaired)
    assert text.count("a loop closure in the graph joins them") == len(joined)
    assert f"the audit's repairs accepted {len(closures)}/" in text and f"{len(closures)} of them now joined" in text
    # with ``loop_gate`` the faked optimum contradicts the repair closures as well: the gate takes
    # them out of the graph, and the pairs no longer say a closure joins them (a red-team pass found
    # report.md still calling them repaired)
    gated = Slam(audit="repair").run(simulated.log)
    for pair in gated.disagreements:
        between = [lp for lp in gated.loops if lp["submaps"] == pair["submaps"]]
        assert pair["repaired"] == any(lp["edge"] and lp["repair"] for lp in between)
        assert pair.get("gated", False) == any(lp.get("gated", False) for lp in between)
    assert any(p.get("gated") for p in gated.disagreements)
    text = slam_module.report(gated)
    assert text.count("; repaired") == sum(p["repaired"] for p in gated.disagreements)
    assert text.count("; the loop gate took") == sum(p.get("gated", False) for p in gated.disagreements)
    # the repair's closures face the neighbours' vote like any loop closure: vetoed, none enters the graph
    votes = Slam._neighbour_votes
    monkeypatch.setattr(Slam, "_neighbour_votes",
                        lambda self, loop, *args: (0, 1) if loop["repair"] else votes(self, loop, *args))
    vetoed = Slam(audit="repair").run(simulated.log)
    tried = [lp for lp in vetoed.loops if lp["repair"]]
    assert any(lp["accepted"] for lp in tried) and not any(lp["edge"] for lp in tried)
    assert vetoed.disagreements and not any(p["repaired"] for p in vetoed.disagreements)


def test_helper_processes_change_nothing(simulated, mapped, monkeypatch):
    """Loop-closure candidates matched by helper processes give the run the same bits as all of
    them matched in this process (the default)."""
    from taichi_match._helper import Helper

    ready, close = [], Helper.close
    monkeypatch.setattr(Helper, "close", lambda helper: (ready.append(helper.ready), close(helper))[1])
    helped = Slam(workers=2).run(simulated.log)
    assert helped.poses.tobytes() == mapped.poses.tobytes()
    assert not any(loop["helper"] for loop in mapped.loops)
    if not any(ready):
        # helpers run at the idle priority: on a machine kept busy by other work they may get no
        # CPU before the run ends (seen with a benchmark running beside the tests)
        pytest.skip("no helper got the CPU to start Taichi before the run ended (a busy machine)")
    assert any(loop["helper"] for loop in helped.loops)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc and the Linux scheduler")
def test_a_helper_runs_at_the_idle_priority_without_taichis_offline_cache():
    """A helper may be killed at any time: without the offline cache it never holds the cache's
    lock file (one killed holding it left the cache locked for every later Taichi process); at
    the idle priority it never slows the loop's own kernels. Read from the process itself."""
    import os

    from taichi_match import MatchOptions
    from taichi_match._helper import Helper

    helper = Helper.start(MatchOptions())
    try:
        pid = helper._process.pid
        with open(f"/proc/{pid}/environ", "rb") as environ:
            assert b"TI_OFFLINE_CACHE=0" in environ.read().split(b"\0")
        helper.collect(wait=True)                          # ready: the priority is set by then
        assert helper.alive
        assert os.sched_getscheduler(pid) == os.SCHED_IDLE
    finally:
        helper.close()


@pytest.fixture(scope="module")
def one_lap():
    return simulate_log(1, laps=1.1).log              # a lap and a bit: 16 loop-closure candidates


@pytest.mark.parametrize("fault", ["never ready", "dies while matching", "its match raises"])
def test_a_helper_that_dies_or_fails_is_replaced_by_this_process(one_lap, monkeypatch, fault):
    """A helper killed before it is ready or while it matches, or one whose match raises, leaves its
    candidates to this process: the same poses as without helpers, no error."""
    from taichi_match import _helper

    alone = Slam(workers=0).run(one_lap)
    assert alone.loops
    given = []

    class Faulty(_helper.Helper):
        @classmethod
        def start(cls, options):
            helper = super().start(options)
            if fault == "never ready":
                helper._process.kill()
            else:
                helper.collect(wait=True)                 # ready before the first candidate
            return helper

        def give(self, tag, maps, guess, window):
            if not self.idle:
                return False
            given.append(tag)
            if fault == "its match raises":               # a map the helper never got
                self._post(("match", tag, "no such map", "no such map", guess, window))
                self.task = tag
                return True
            taken = super().give(tag, maps, guess, window)
            self._process.kill()
            return taken

    monkeypatch.setattr("taichi_match.slam.Helper", Faulty)
    result = Slam(workers=1).run(one_lap)
    assert result.poses.tobytes() == alone.poses.tobytes()
    assert not any(loop["helper"] for loop in result.loops)
    assert (not given) if fault == "never ready" else len(given) == 1      # then it is no longer used


def test_same_input_same_bits(short_run):
    first, second = Slam().run(short_run.log), Slam().run(short_run.log)
    assert first.poses.tobytes() == second.poses.tobytes()


@pytest.mark.parametrize("frames", [False, True])
def test_outputs_load(short_run, tmp_path, frames):
    from taichi_match.io import read_ros_map

    result = Slam(submap_frames=frames).run(short_run.log)
    paths = write_outputs(result, tmp_path / "out", source="simulated")
    stamps, poses = read_tum(paths["trajectory"])
    np.testing.assert_array_equal(stamps, short_run.log.timestamps)
    np.testing.assert_allclose(poses[:, :2], result.poses[:, :2], atol=1e-6)
    grid = read_ros_map(paths["map"])
    assert grid.shape == result.map.shape and grid.resolution == pytest.approx(0.05)
    graph, values = gtsam.readG2o(str(paths["graph"]), False)
    n, m = len(short_run.log), len(result.frames)
    half = result.options.submap_scans // 2
    assert m == (n - 1) // half + 1                                   # a submap every ``half`` scans
    if frames:                                        # scans 0..n-1, then frame i at 2**30 + i
        assert sorted(values.keys()) == list(range(n)) + [2**30 + i for i in range(m)]
        assert graph.size() >= n - 1 + n                              # odometry, a match or member edge per scan
    else:                                                             # a frame is its first scan's node
        assert sorted(values.keys()) == list(range(n)) and graph.size() >= n - 1
        np.testing.assert_array_equal(result.frames, result.poses[::half])
    for k in values.keys():
        pose = values.atPose2(k)
        expected = result.poses[k] if k < n else result.frames[k - 2**30]
        np.testing.assert_allclose([pose.x(), pose.y(), pose.theta()], expected, rtol=1e-5, atol=1e-5)  # g2o: 6 digits
    assert "scan-to-submap matches accepted" in paths["report"].read_text()
    assert result.match_parts.shape == (result.scan_matches[1], 3) and np.all(result.match_parts >= 0)
    np.testing.assert_array_equal(result.match_seconds, result.match_parts.sum(axis=1))
    assert "Front-end match, median" in paths["report"].read_text()
    evo_file = pytest.importorskip("evo.tools.file_interface")
    trajectory = evo_file.read_tum_trajectory_file(str(paths["trajectory"]))
    assert trajectory.num_poses == len(short_run.log)
    with pytest.raises(FileExistsError):
        write_outputs(result, tmp_path / "out")
    write_outputs(result, tmp_path / "out", force=True)


def test_cli_slam(short_run, tmp_path, capsys):
    log_path = tmp_path / "run.log"
    write_carmen(log_path, short_run.log)
    assert main(["slam", str(log_path), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "trajectory.tum").exists() and (tmp_path / "out" / "map.pgm").exists()
    assert "the audit (the map's self-check): 0 pairs of submaps disagreed" in capsys.readouterr().out
    assert main(["slam", str(log_path), "--out", str(tmp_path / "out")]) == 2          # outputs exist
    assert "--force" in capsys.readouterr().err
    truncated = tmp_path / "truncated.log"
    truncated.write_text(log_path.read_text()[:-200])                                  # cut mid-line
    assert main(["slam", str(truncated), "--out", str(tmp_path / "t")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("taichi-match: error:") and "Traceback" not in err


def test_cli_slam_refuses_options_that_do_not_apply_to_the_input(short_run, tmp_path, capsys):
    """A bag's topics given for a CARMEN log, or a CARMEN log's maximum range for a bag, would be
    ignored: they are refused before any work."""
    log_path = tmp_path / "run.log"
    write_carmen(log_path, short_run.log)
    for flag in ("--scan-topic", "--odom-topic"):
        assert main(["slam", str(log_path), "--out", str(tmp_path / "out"), flag, "/scan"]) == 2
        assert f"{flag} applies to ROS bags only" in capsys.readouterr().err
    bag = tmp_path / "run.bag"
    bag.write_bytes(b"")
    assert main(["slam", str(bag), "--out", str(tmp_path / "out"), "--max-range", "30"]) == 2
    assert "--max-range applies to CARMEN logs only" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_cli_slam_submap_frames(short_run, tmp_path):
    """Submap frames (the default) reach the graph file, a node per submap beyond the scans';
    ``--no-submap-frames`` leaves the scans' nodes only."""
    log_path = tmp_path / "run.log"
    write_carmen(log_path, short_run.log)
    n, half = len(short_run.log), SlamOptions().submap_scans // 2
    for flags, nodes in (([], n + (n - 1) // half + 1), (["--submap-frames"], n + (n - 1) // half + 1),
                         (["--no-submap-frames"], n)):
        out = tmp_path / f"out{len(flags)}{flags[0][2:4] if flags else ''}"
        assert main(["slam", str(log_path), "--out", str(out)] + flags) == 0
        _, values = gtsam.readG2o(str(out / "graph.g2o"), False)
        assert values.size() == nodes, flags


@pytest.mark.parametrize("flag, field, values", [("--share-coarse", "share_coarse", (True, False)),
                                                 ("--crop-target", "crop_target", (True, False)),
                                                 ("--workers", "workers", (1, 0)),
                                                 ("--loop-ties", "loop_ties", (5.0, None)),
                                                 ("--solver", "solver", ("isam2", "batch")),
                                                 ("--free-margin", "free_margin", (0.2, 0.1)),
                                                 ("--loop-radius", "loop_radius", (8.0, 3.0)),
                                                 ("--audit", "audit", ("report", "repair")),
                                                 ("--front-end-inflation", "front_end_inflation", (2.0, 6.0)),
                                                 ("--gate-inflation", "gate_inflation", (6.0, 2.0)),
                                                 ("--loop-gate", "loop_gate", (30.0, 16.27)),
                                                 ("--loop-growth", "loop_growth", (0.2, 0.1)),
                                                 ("--robust-kernel", "robust_kernel", (3.0, 1.5)),
                                                 ("--jump-check", "jump_check", (5.0, 3.0)),
                                                 ("--turn-edge", "turn_edge", (0.5, math.radians(60.0)))])
def test_cli_slam_speed_options_reach_the_loop(short_run, tmp_path, flag, field, values):
    """The speed options' flags set their field of the run's options (recorded in report.md),
    which is the default without them ("off": None)."""
    log_path = tmp_path / "run.log"
    write_carmen(log_path, short_run.log)
    flags = [flag] if values[0] is True else [flag, str(values[0])]
    off = [([flag, "off"], None)] if flag in ("--loop-ties", "--audit", "--loop-gate", "--jump-check",
                                              "--turn-edge") else []
    runs = [(flags, values[0]), ([], values[1])] + off
    for k, (args, value) in enumerate(runs):
        out = tmp_path / f"out{k}"
        assert main(["slam", str(log_path), "--out", str(out), *args]) == 0
        assert f"{field}={value!r}" in (out / "report.md").read_text()


def test_cli_slam_odometry_model_and_loop_consistency_reach_the_loop(short_run, tmp_path):
    """``--odometry-sd`` (five numbers) and ``--no-loop-consistency`` set their fields, recorded in
    report.md; without them the defaults."""
    import math

    log_path = tmp_path / "run.log"
    write_carmen(log_path, short_run.log)
    sd = (0.03, 0.04, 0.006, 0.002, 0.001)
    out = tmp_path / "set"
    flags = ["--odometry-sd", *map(str, sd), "--no-loop-consistency"]
    assert main(["slam", str(log_path), "--out", str(out), *flags]) == 0
    report = (out / "report.md").read_text()
    assert f"odometry_sd={sd!r}" in report and "loop_consistency=False" in report
    out = tmp_path / "default"
    assert main(["slam", str(log_path), "--out", str(out)]) == 0
    report = (out / "report.md").read_text()
    default = (0.02, 0.02, math.radians(0.3), 0.005, math.radians(0.1))
    assert f"odometry_sd={default!r}" in report and "loop_consistency=True" in report


@pytest.mark.parametrize("args", [["--loop-gate", "-1"], ["--gate-inflation", "0"], ["--submap-scans", "3"],
                                  ["--max-ray", "-3"], ["--resolution", "nan"], ["--loop-ties", "-2"],
                                  ["--odometry-sd", "0.02", "0.02", "0.005", "0.005", "0"], ["--jump-check", "0.5"],
                                  ["--robust-kernel", "0"], ["--loop-growth", "-1"]])
def test_cli_slam_a_refused_value_names_its_flag(short_run, tmp_path, capsys, args):
    """A value ``SlamOptions`` refuses is a one-line error (exit 2) that names the flag typed, before
    any work and without a traceback."""
    log_path = tmp_path / "run.log"
    write_carmen(log_path, short_run.log)
    capsys.readouterr()
    assert main(["slam", str(log_path), "--out", str(tmp_path / "out"), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"taichi-match: error: {args[0]}: ") and "Traceback" not in err
    assert not (tmp_path / "out" / "trajectory.tum").exists()


def test_cli_slam_front_end_lookup_and_levels_reach_the_front_end(short_run, tmp_path, capsys):
    """``--front-end-levels`` and ``--front-end-lookup`` set the front end's ``MatchOptions`` (and
    not the loop closures'), recorded in report.md; bad values are one-line errors."""
    log_path = tmp_path / "run.log"
    write_carmen(log_path, short_run.log)
    for k, (args, levels, lookup) in enumerate([([], 2, "bilinear"),
                                                (["--front-end-levels", "3", "--front-end-lookup", "nearest"], 3,
                                                 "nearest")]):
        out = tmp_path / f"out{k}"
        assert main(["slam", str(log_path), "--out", str(out), *args]) == 0
        text = (out / "report.md").read_text()
        front, loops = text.split("scan_matcher=")[1], text.split("scan_matcher=")[0].split("matcher=")[1]
        assert f"levels={levels}," in front and f"interpolation='{lookup}'" in front
        assert "levels=3," in loops and "interpolation='nearest'" in loops
    capsys.readouterr()
    assert main(["slam", str(log_path), "--out", str(tmp_path / "bad"), "--front-end-levels", "0"]) == 2
    assert "levels" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["slam", str(log_path), "--out", str(tmp_path / "bad2"), "--front-end-lookup", "cubic"])


def test_cli_slam_loop_grid_edge_reaches_the_loop_closures_only(short_run, tmp_path, capsys):
    """``--loop-grid-edge unknown`` sets the loop closures' ``MatchOptions.grid_edge`` (not the front
    end's), recorded in report.md; the default stays "free"; another value is refused."""
    log_path = tmp_path / "run.log"
    write_carmen(log_path, short_run.log)
    for k, (args, edge) in enumerate([([], "free"), (["--loop-grid-edge", "unknown"], "unknown")]):
        out = tmp_path / f"out{k}"
        assert main(["slam", str(log_path), "--out", str(out), *args]) == 0
        text = (out / "report.md").read_text()
        front, loops = text.split("scan_matcher=")[1], text.split("scan_matcher=")[0].split("matcher=")[1]
        assert f"grid_edge='{edge}'" in loops and "grid_edge='free'" in front
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["slam", str(log_path), "--out", str(tmp_path / "bad"), "--loop-grid-edge", "Unknown"])


def test_an_output_folder_that_cannot_be_written_is_refused_before_any_work(short_run, tmp_path, monkeypatch,
                                                                            capsys):
    """A read-only place for the outputs (``os.access`` says so, as on a read-only file system)
    is bad input before the run, not an error after it."""
    log_path = tmp_path / "run.log"
    write_carmen(log_path, short_run.log)
    monkeypatch.setattr("taichi_match._slam_outputs.os.access", lambda path, mode: False)
    ran = []
    monkeypatch.setattr(Slam, "run", lambda self, *args, **kwargs: ran.append(1))
    assert main(["slam", str(log_path), "--out", str(tmp_path / "ro" / "out")]) == 2
    assert "cannot write into" in capsys.readouterr().err and not ran


def test_carmen_round_trip(short_run, tmp_path):
    path = tmp_path / "run.log"
    write_carmen(path, short_run.log)
    back = read_carmen(path)
    assert len(back) == len(short_run.log)
    for a, b in zip(back.scans, short_run.log.scans):
        np.testing.assert_allclose(a.angles, b.angles, atol=1e-12)
        np.testing.assert_allclose(a.ranges, b.ranges, atol=5e-4)
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-6)


def test_bad_readings_are_skipped(short_run):
    """NaN, negative and zero ranges are ignored (scans.beam_segments): the run completes with finite
    poses close to those of the clean log."""
    rng = np.random.default_rng(0)
    scans = []
    for scan in short_run.log.scans:
        r = np.array(scan.ranges)
        bad = rng.random(len(r)) < 0.1
        r[bad] = rng.choice([np.nan, -1.0, 0.0, np.inf], int(bad.sum()))
        scans.append(dataclasses.replace(scan, ranges=r))
    result = Slam().run(LaserLog(tuple(scans), short_run.log.odometry))
    assert np.all(np.isfinite(result.poses))
    errors = trajectory_errors(result.poses, short_run.truth)
    assert errors["ate_m"] <= 0.10, errors


def test_bad_logs_raise(short_run):
    with pytest.raises(InvalidOptionError, match="no scan"):
        Slam().run(LaserLog((), np.zeros((0, 4))))
    still = tuple(dataclasses.replace(s, pose=np.zeros(3)) for s in short_run.log.scans)
    with pytest.raises(InvalidOptionError, match="no odometry"):
        Slam().run(LaserLog(still, np.zeros((0, 4))))
    # no scan with a usable reading: refused before the first scan is matched, not after the loop
    blind = tuple(dataclasses.replace(s, ranges=np.full(len(s.ranges), np.nan)) for s in short_run.log.scans)
    steps = []
    with pytest.raises(InvalidOptionError, match="no usable beam"):
        Slam().run(LaserLog(blind, short_run.log.odometry), progress=lambda k, n: steps.append(k))
    assert steps == []


def test_truncated_log_raises(short_run, tmp_path):
    path = tmp_path / "run.log"
    write_carmen(path, short_run.log)
    path.write_text(path.read_text()[:-200])
    with pytest.raises(LogFormatError):
        read_carmen(path)


@pytest.mark.parametrize("field, value", [("submap_scans", 5), ("submap_scans", 2), ("resolution", 0.0),
                                          ("loop_radius", -1.0), ("odometry_sd", (0.1, 0.1)),
                                          ("odometry_sd", (0.1, 0.1, 0.1, 0.0, 0.1)), ("max_ray_length", math.nan),
                                          ("target_refresh", 0), ("target_refresh", 2.0), ("target_refresh", True),
                                          ("loop_consistency", 1), ("share_coarse", 1), ("workers", -1),
                                          ("workers", 1.0), ("workers", True), ("workers", 65), ("workers", None),
                                          ("resolution", 0.002), ("max_ray_length", 300.0),
                                          ("free_margin", -0.1), ("free_margin", math.nan), ("free_margin", True),
                                          ("free_margin", 20.0), ("audit", "yes"), ("audit", True),
                                          ("audit", np.array(["repair", "report"])),
                                          ("front_end_inflation", 0.0), ("front_end_inflation", math.inf),
                                          ("front_end_inflation", "4"), ("front_end_inflation", True),
                                          ("gate_inflation", 0.0), ("gate_inflation", -1.0),
                                          ("gate_inflation", math.nan), ("gate_inflation", "2"),
                                          ("gate_inflation", True), ("jump_check", 0.5), ("jump_check", math.inf),
                                          ("jump_check", "3"), ("jump_check", True),
                                          ("loop_gate", 0.0), ("loop_gate", -1.0), ("loop_gate", math.nan),
                                          ("loop_gate", math.inf), ("loop_gate", "16"), ("loop_gate", True)])
def test_options_are_checked(field, value):
    with pytest.raises(InvalidOptionError):
        SlamOptions(**{field: value})


@pytest.mark.parametrize("inflation", [1.0, 2.5])
def test_front_end_edges_carry_the_inflated_match_covariance(short_run, inflation):
    """Each scan matched within the odometry gate has one robust edge from its submap's frame (key
    ``FRAME_KEY`` + the submap's index) whose covariance is the match's, rotated into the
    relative pose's own axes (as gtsam's Pose2 wants it, done here by hand), times
    ``front_end_inflation``."""
    import gtsam

    result = Slam(front_end_inflation=inflation).run(short_run.log)
    robust = {}
    for i in range(result.graph.size()):
        factor = result.graph.at(i)
        if isinstance(factor, gtsam.BetweenFactorPose2) and isinstance(factor.noiseModel(), gtsam.noiseModel.Robust):
            robust.setdefault(tuple(factor.keys()), []).append(factor)
    edges = [record for record in result.scans if record["edge"]]
    assert len(edges) > 10
    for record in edges:
        (factor,) = robust[(FRAME_KEY + record["submap"], record["scan"])]
        c, s = math.cos(record["pose"][2]), math.sin(record["pose"][2])
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        expected = inflation * rotation.T @ np.asarray(record["covariance"]) @ rotation
        np.testing.assert_allclose(factor.noiseModel().noise().covariance(), expected, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("refresh", [1, 3, 5])
def test_target_is_cast_again_after_target_refresh_scans(short_run, monkeypatch, refresh):
    """The front end casts its target for the first scan matched against it, then again once
    ``target_refresh`` scans have passed or the graph was optimised (every ``submap_scans // 2``
    scans, when the target changes): counted against the scans matched, independently."""
    casts = []
    original = Slam._submap_grid

    def counting(self, log, submap, est, cast=None, bounds=None):
        if cast is not None:                       # the front end's target (loop closing passes none)
            casts.append(submap.index)
        return original(self, log, submap, est, cast, bounds)

    monkeypatch.setattr(Slam, "_submap_grid", counting)
    result = Slam(target_refresh=refresh).run(short_run.log)
    size, half = result.options.submap_scans, result.options.submap_scans // 2
    matched = [s["scan"] for s in result.scans if s["pose"] is not None]
    # the first submap is the target of scans 1 .. size - 1, each later one of the next half
    # scans; within a target's scans a cast happens at its first matched scan and then at the first
    # matched scan at least ``refresh`` later
    period = {k: max(0, (k - size) // half + 1) for k in matched}
    expected = 0
    for p in sorted(set(period.values())):
        last = None
        for k in (k for k in matched if period[k] == p):
            if last is None or k - last >= refresh:
                expected, last = expected + 1, k
    assert len(casts) == expected
    if refresh == 1:
        assert len(casts) == len(matched)


@pytest.mark.parametrize("share", [False, True])
def test_share_coarse_prepares_only_the_finest_level_between_whole_casts(short_run, monkeypatch, share):
    """With ``share_coarse`` every cast of the front end's target but the first of each period
    (a new target, or the first after an optimisation) takes its coarser levels from that first
    cast's; without it none does. Counted against the scans matched, independently."""
    shared = []
    original = Matcher.prepare

    def recording(self, grid, *args, coarse_from=None, **kwargs):
        prepared = original(self, grid, *args, coarse_from=coarse_from, **kwargs)
        if coarse_from is not None:
            shared.append(prepared.level(1) is coarse_from.level(1) and prepared.level(2) is coarse_from.level(2))
        return prepared

    monkeypatch.setattr(Matcher, "prepare", recording)
    result = Slam(share_coarse=share).run(short_run.log)
    size, half = result.options.submap_scans, result.options.submap_scans // 2
    matched = [s["scan"] for s in result.scans if s["pose"] is not None]
    periods = {max(0, (k - size) // half + 1) for k in matched}
    assert shared == ([True] * (len(matched) - len(periods)) if share else [])
    accepted, tried = result.scan_matches
    assert accepted >= 0.9 * tried


@pytest.mark.parametrize("other", [{"target_refresh": 2}, {"share_coarse": True}])
def test_crop_target_refuses_a_target_kept_between_scans(other):
    with pytest.raises(InvalidOptionError, match="crop_target"):
        SlamOptions(crop_target=True, **other)
    SlamOptions(crop_target=False, **other)


def test_the_front_end_target_is_cropped_around_the_scan(short_run, monkeypatch):
    """With ``crop_target`` the front end matches each scan against the part of its
    target around where the scan lands: mostly smaller than the whole cast, and holding every cell
    of the whole cast that a known cell of the scan lands on at the pose the match accepted;
    without it, the whole cast."""
    casts = []
    original = Slam._submap_grid

    def recording(self, log, submap, est, cast=None, bounds=None):
        grid = original(self, log, submap, est, cast, bounds)
        if cast is not None:                       # the front end's target (loop closing passes none)
            casts.append((grid, original(self, log, submap, est, cast)))
        return grid

    monkeypatch.setattr(Slam, "_submap_grid", recording)
    for crop in (False, True):
        casts.clear()
        slam = Slam(crop_target=crop)
        matches = []
        match = slam._scan_matcher.match
        slam._scan_matcher.match = (lambda a, b, guess, **kw: matches.append((b, match(a, b, guess, **kw)))
                                    or matches[-1][1])
        result = slam.run(short_run.log)
        assert len(casts) == len(matches) == result.scan_matches[1]
        smaller = sum(grid.prob.size < whole.prob.size for grid, whole in casts)
        assert smaller >= 0.5 * len(casts) if crop else smaller == 0
        for (grid, whole), (b, res) in zip(casts, matches):
            if res.accepted:
                points = transform_points(res.pose, b.cell_centres(*np.nonzero(b.known)))
                rows, cols = whole.cell_of(points)
                on = (rows >= 0) & (cols >= 0) & (rows < whole.shape[0]) & (cols < whole.shape[1])
                rows, cols = grid.cell_of(points[on])
                assert rows.min() >= 0 and cols.min() >= 0 and rows.max() < grid.shape[0] and cols.max() < grid.shape[1]


def test_loop_closures_vote_on_a_new_one():
    """A loop closure agrees with the loop closures already in the graph near both its frames when
    they predict its relative pose through the estimates' short chains; one slid 2 m along a
    corridor (the aliasing that derailed aces) does not; one with no neighbours gets no vote."""
    from taichi_match import compose, inverse

    # out along a corridor 1 m a scan and back 1 m to the side: scan k and 99 - k face each other
    k = np.arange(100.0)
    est = np.column_stack([np.where(k < 50, k, 99.0 - k), np.where(k < 50, 0.0, 1.0), np.where(k < 50, 0.0, np.pi)])
    travelled = k
    cov = np.diag([0.03**2, 0.03**2, 0.005**2])

    def loop(a, b, offset=(0.0, 0.0, 0.0)):
        return {"frames": (a, b), "pose": compose(compose(inverse(est[a]), est[b]), offset), "covariance": cov}

    edges = [loop(10, 89), loop(15, 83)]
    slam = Slam()
    assert slam._neighbour_votes(loop(12, 87), edges, est, travelled) == (2, 0)
    assert slam._neighbour_votes(loop(12, 87, (2.0, 0.0, 0.0)), edges, est, travelled) == (0, 2)
    assert slam._neighbour_votes(loop(12, 87, (0.0, 0.0, 0.2)), edges, est, travelled) == (0, 2)   # 11.5 degrees
    assert slam._neighbour_votes(loop(40, 59), edges, est, travelled) == (0, 0)


def test_cast_scan_against_geometry():
    """A laser in the plan's lower left corridor looking along +x reads the distance to the corridor's
    far end wall (the outer rooms' wall, 0.15 m thick, its outer face at x = 21.5 m), and no return off the
    map."""
    world = floor_plan(0)
    pose = (4.0, 3.75, 0.0)
    r = cast_scan(world, pose, np.array([0.0]), max_range=40.0, noise=0.0)
    assert r[0] == pytest.approx(21.5 - 0.15 - 4.0, abs=0.05)
    r = cast_scan(world, (-5.0, -5.0, 0.0), np.array([math.pi]), max_range=3.0, noise=0.0)
    assert r[0] == 3.0


def test_trajectory_errors_match_evo():
    metrics = pytest.importorskip("evo.core.metrics")
    from evo.core.trajectory import PoseTrajectory3D
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    reference = np.cumsum(rng.normal(0, 0.3, (100, 3)), axis=0)
    noisy = reference + rng.normal(0, 0.05, (100, 3))
    c, s = math.cos(0.3), math.sin(0.3)
    estimate = np.column_stack([c * noisy[:, 0] - s * noisy[:, 1] + 1, s * noisy[:, 0] + c * noisy[:, 1] - 2,
                                noisy[:, 2] + 0.3])

    def trajectory(p):
        quat = Rotation.from_euler("z", p[:, 2:3]).as_quat()[:, [3, 0, 1, 2]]
        return PoseTrajectory3D(positions_xyz=np.column_stack([p[:, :2], np.zeros(len(p))]),
                                orientations_quat_wxyz=quat, timestamps=np.arange(len(p), dtype=float))

    def rmse(metric, aligned):
        ref, est = trajectory(reference), trajectory(estimate)
        if aligned:
            est.align(ref, correct_scale=False)
        metric.process_data((ref, est))
        return metric.get_statistic(metrics.StatisticsType.rmse)

    ours = trajectory_errors(estimate, reference)
    assert ours["ate_m"] == pytest.approx(rmse(metrics.APE(metrics.PoseRelation.translation_part), True), rel=1e-9)
    assert ours["ate_deg"] == pytest.approx(rmse(metrics.APE(metrics.PoseRelation.rotation_angle_deg), True),
                                            rel=1e-9)
    kw = dict(delta=10, delta_unit=metrics.Unit.frames, all_pairs=True)
    assert ours["rpe_m"] == pytest.approx(rmse(metrics.RPE(metrics.PoseRelation.translation_part, **kw), False),
                                          rel=1e-9)
    assert ours["rpe_deg"] == pytest.approx(rmse(metrics.RPE(metrics.PoseRelation.rotation_angle_deg, **kw), False),
                                            rel=1e-9)


def test_cli_demo_slam(capsys):
    """The README's demo: exit 0, the error against the simulated truth and the audit's finding
    (none: the run is right) printed."""
    assert main(["demo-slam", "--plot", ""]) == 0
    out = capsys.readouterr().out
    assert "against the simulated truth: ATE" in out and "the odometry alone" in out
    assert "0 pairs of submaps disagreed" in out


def test_cli_never_writes_over_its_inputs(short_run, tmp_path, capsys):
    """A log or a reference named like an output in the output folder: exit 2 before any work,
    even with --force, and the file intact; so also when an output is a folder."""
    folder = tmp_path / "d"
    folder.mkdir()
    log_path = folder / "report.md"
    write_carmen(log_path, short_run.log)
    before = log_path.read_bytes()
    assert main(["slam", str(log_path), "--out", str(folder), "--force"]) == 2
    assert log_path.read_bytes() == before and not (folder / "trajectory.tum").exists()
    from taichi_match.logs import write_tum

    write_carmen(tmp_path / "run.log", short_run.log)
    write_tum(folder / "trajectory.tum", short_run.log.timestamps, short_run.truth)
    before = (folder / "trajectory.tum").read_bytes()
    assert main(["slam", str(tmp_path / "run.log"), "--out", str(folder), "--force",
                 "--reference", str(folder / "trajectory.tum")]) == 2
    assert (folder / "trajectory.tum").read_bytes() == before
    (tmp_path / "e" / "graph.g2o").mkdir(parents=True)
    assert main(["slam", str(tmp_path / "run.log"), "--out", str(tmp_path / "e"), "--force"]) == 2
    assert not (tmp_path / "e" / "map.yaml").exists()
    err = capsys.readouterr().err
    assert err.count("\n") == 3 and "Traceback" not in err


def test_cli_reference_must_match_the_scans(short_run, tmp_path, capsys):
    from taichi_match.logs import write_tum

    write_carmen(tmp_path / "run.log", short_run.log)
    write_tum(tmp_path / "late.tum", short_run.log.timestamps + 5.0, short_run.truth)
    assert main(["slam", str(tmp_path / "run.log"), "--out", str(tmp_path / "o"),
                 "--reference", str(tmp_path / "late.tum")]) == 2
    assert "timestamps" in capsys.readouterr().err and not (tmp_path / "o" / "trajectory.tum").exists()


@pytest.mark.parametrize("bad", [["--submap-scans", "1e9"], ["--loop-ties", "abc"], ["--solver", "lm"]])
def test_cli_argument_errors_are_one_line(capsys, bad):
    with pytest.raises(SystemExit) as exit_info:
        main(["slam", "x.log", "--out", "o", *bad])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("taichi-match: error:") and err.count("\n") == 1


def test_useless_geometry_and_broken_odometry_are_refused_before_any_work(short_run, tmp_path, capsys):
    with pytest.raises(InvalidOptionError, match="cells"):
        SlamOptions(resolution=10.0)                       # a 20 m ray across 2 cells
    jumped = tuple(dataclasses.replace(s, pose=s.pose + (2000.0 if k >= 7 else 0.0) * np.array([1.0, 0.0, 0.0]))
                   for k, s in enumerate(short_run.log.scans))
    with pytest.raises(InvalidOptionError, match=r"jumps 2000\.\d m between scans 6 and 7"):
        Slam().run(LaserLog(jumped, short_run.log.odometry))
    from taichi_match.slam import output_paths

    with pytest.raises(InvalidOptionError, match="named"):
        output_paths("")
    log_path = tmp_path / "run.log"
    write_carmen(log_path, short_run.log)
    assert main(["slam", str(log_path), "--out", ""]) == 2
    assert "must be named" in capsys.readouterr().err


def test_cli_exits_1_when_no_scan_match_is_accepted(short_run, tmp_path, capsys):
    # rays cut at 1 m see no wall (the corridor's walls are farther): nothing to match
    log_path = tmp_path / "run.log"
    write_carmen(log_path, short_run.log)
    assert main(["slam", str(log_path), "--out", str(tmp_path / "out"), "--max-ray", "1.0"]) == 1
    assert "no scan match was accepted" in capsys.readouterr().err
    assert (tmp_path / "out" / "trajectory.tum").exists()


def test_cli_exits_1_when_most_scans_match_nothing(short_run, tmp_path, capsys):
    # each scan's beams in reverse order (a mirrored laser): the scans no longer overlap their
    # submaps, a few matches at most are accepted, and the run exited 0 with the odometry's trajectory
    flipped = LaserLog(tuple(dataclasses.replace(s, ranges=s.ranges[::-1].copy()) for s in short_run.log.scans),
                       short_run.log.odometry)
    log_path = tmp_path / "flipped.log"
    write_carmen(log_path, flipped)
    assert main(["slam", str(log_path), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert "scan match" in err and "odometry's" in err
    assert (tmp_path / "out" / "trajectory.tum").exists()


def _jumped(log, k, jump, spike=False):
    """``log`` with its odometry moved by ``jump`` from scan ``k`` on (or, a ``spike``, at ``k`` only)."""
    return LaserLog(tuple(dataclasses.replace(s, pose=compose(np.array(jump), s.pose) if j == k or (j > k and not spike)
                                              else s.pose) for j, s in enumerate(log.scans)), log.odometry)


@pytest.mark.parametrize("jump", [(19.0, 0.0, 0.0), (3.0, 0.0, 0.0), (0.0, 0.0, 1.0), (2.0, -1.0, 0.5)])
@pytest.mark.parametrize("spike", [False, True])
def test_an_odometry_jump_is_bridged_by_a_search(simulated, jump, spike):
    """The odometry jumps a third of the way round by ``jump`` (about the origin), and stays there
    (a reset: each alone left the trajectory 1.4-8.9 m and 1-29 degrees off with 95 % of the scan
    matches accepted) or, as a ``spike``, jumps back at the next scan (one bad reading; 3 m left
    it 1.5 m off): the search around the previous scan finds the scan, the jump's step leaves the
    graph (a spike's next scan takes its step from the reading before the jump), and the run
    meets the ATE targets against the exact truth."""
    k = len(simulated.log) // 3
    result = Slam().run(_jumped(simulated.log, k, jump, spike))
    errors = trajectory_errors(result.poses, simulated.truth)
    assert errors["ate_m"] <= 0.10 and errors["ate_deg"] <= 1.0, errors
    checks = [(c["scan"], c["jump"], c["spike"]) for c in result.jump_checks]
    assert checks == ([(k, True, False), (k + 1, False, True)] if spike else [(k, True, False)])
    for check, (before, scan) in zip(result.jump_checks, [(k - 1, k), (k - 1, k + 1)]):
        truth = compose(inverse(simulated.truth[before]), simulated.truth[scan])
        found = check["step"]
        assert math.hypot(*(found[:2] - truth[:2])) < 0.05 and abs(wrap_angle(found[2] - truth[2])) < math.radians(1)
    joined = {tuple(result.graph.at(i).keys()) for i in range(result.graph.size()) if result.graph.at(i) is not None}
    assert (k - 1, k) not in joined                                    # the jump's odometry step left
    assert ((k - 1, k + 1) in joined and (k, k + 1) not in joined) if spike else (k, k + 1) in joined


@pytest.mark.parametrize("jump, spike", [((18.0, 0.0, 0.0), False), ((0.0, 0.0, 1.0), True)])
def test_an_odometry_jump_at_a_corner_is_bridged(simulated, jump, spike):
    """At scan 100 the simulated robot turns 93 degrees between two scans: the search turns as far
    as the odometry did (a window of the run's usual turns alone missed every jump there)."""
    k = 100
    about = simulated.log.scans[k - 1].pose
    motion = compose(about, compose(np.array(jump), inverse(about)))
    result = Slam().run(_jumped(simulated.log, k, motion, spike))
    errors = trajectory_errors(result.poses, simulated.truth)
    assert errors["ate_m"] <= 0.10 and errors["ate_deg"] <= 1.0, errors
    assert [(c["scan"], c["jump"]) for c in result.jump_checks][:1] == [(k, True)]


def test_cli_slam_reports_an_odometry_jump(short_run, tmp_path, capsys):
    k = len(short_run.log) // 2
    log_path = tmp_path / "jumped.log"
    write_carmen(log_path, _jumped(short_run.log, k, (5.0, 0.0, 0.0)))
    assert main(["slam", str(log_path), "--out", str(tmp_path / "out")]) == 0
    said = f"the odometry jumps before scan {k}: bridged by a scan match"
    assert said in capsys.readouterr().out
    assert said in (tmp_path / "out" / "report.md").read_text()


def test_add_then_finish_bridges_a_spike_as_run_does(short_run):
    """The jump check and the spike's next scan run the same scan by scan (``add``) as over the
    whole log (``run``), bit for bit."""
    log = _jumped(short_run.log, len(short_run.log) // 2, (4.0, -1.0, 0.3), spike=True)
    reference = Slam().run(log)
    assert [(c["jump"], c["spike"]) for c in reference.jump_checks] == [(True, False), (False, True)]
    slam = Slam()
    for scan in log.scans:
        slam.add(scan)
    result = slam.finish()
    assert result.poses.tobytes() == reference.poses.tobytes()
    assert len(result.jump_checks) == 2


@pytest.mark.parametrize("name, overrides", [("orebro", {}), ("fhw", {}), ("csail", {"max_ray_length": 10.0})])
def test_a_large_odometry_step_that_is_right_is_not_a_jump(name, overrides):
    """Real logs whose front end fails at a few large odometry steps (orebro: turns of 40-44
    degrees, a step of 1.35 m; fhw at scan 57 and csail at scan 201 with 10 m rays, where the
    search finds a pose 0.6-3.2 m away that fits the submap better than the refused match, and
    which a red-team pass and a wider search window made false jumps): no jump, and the
    trajectory is the one without the check, bit for bit."""
    logs = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "logs", name)
    found = [f for f in (os.listdir(logs) if os.path.isdir(logs) else []) if ".log" in f and "reference" not in f]
    if not found:
        pytest.skip(f"../shared/logs/{name} is not here")
    log = read_carmen(os.path.join(logs, found[0]))
    checked, unchecked = Slam(**overrides).run(log), Slam(jump_check=None, **overrides).run(log)
    assert len(checked.jump_checks) >= 1 and not any(c["jump"] or c["spike"] for c in checked.jump_checks)
    assert np.array_equal(checked.poses, unchecked.poses) and unchecked.jump_checks == []


def test_timestamps_must_increase(short_run):
    scans = list(short_run.log.scans)
    scans[3], scans[4] = scans[4], scans[3]
    with pytest.raises(InvalidOptionError, match="timestamps"):
        Slam().run(LaserLog(tuple(scans), short_run.log.odometry))


def test_grid_size_is_checked_before_casting(short_run):
    from taichi_match.scans import scans_to_grid

    with pytest.raises(InvalidOptionError, match="cells"):
        scans_to_grid(short_run.log.scans[:1], np.zeros((1, 3)), resolution=1e-4)


def test_flaser_with_extra_fields_raises(short_run, tmp_path):
    path = tmp_path / "run.log"
    write_carmen(path, short_run.log)
    lines = path.read_text().splitlines()
    lines[3] = lines[3].replace("FLASER 181", "FLASER 180", 1)          # one range read as a pose field
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(LogFormatError, match="fields"):
        read_carmen(path)


def test_empty_scans_are_skipped(short_run):
    """Scans without one usable reading (all NaN or zero) keep the odometry's prediction; the others
    are mapped as before."""
    scans = list(short_run.log.scans)
    for k in (0, 5, 6):
        scans[k] = dataclasses.replace(scans[k], ranges=np.full(len(scans[k].ranges), np.nan))
    result = Slam().run(LaserLog(tuple(scans), short_run.log.odometry))
    assert np.all(np.isfinite(result.poses))
    skipped = [rec["scan"] for rec in result.scans if rec["pose"] is None]
    assert {5, 6} <= set(skipped)
    assert trajectory_errors(result.poses, short_run.truth)["ate_m"] <= 0.10


def test_outputs_are_readable_like_any_new_file(short_run, tmp_path):
    """Every output gets the mode open() gives a new file under the umask (the map was 0600)."""
    import os

    mask = os.umask(0o022)
    os.umask(mask)
    paths = write_outputs(Slam().run(short_run.log), tmp_path / "out")
    for path in paths.values():
        assert (path.stat().st_mode & 0o777) == (0o666 & ~mask), path


def test_overlap_share_by_hand():
    """B (10 x 10 cells of 0.1 m, all known) on A (the same frame, only its left 4 columns known):
    40 % of B's cells land on A's known cells; moved 2 m away, none; a B without known cells, 0."""
    from taichi_match import GridMap
    from taichi_match.slam import Footprint, overlap_share

    a_prob = np.full((10, 10), np.nan)
    a_prob[:, :4] = 0.2
    a, b = Footprint(GridMap(a_prob, 0.1), stride=1), Footprint(GridMap(np.full((10, 10), 0.2), 0.1), stride=1)
    assert overlap_share(a, b, (0.0, 0.0, 0.0)) == pytest.approx(0.4)
    assert overlap_share(a, b, (0.2, 0.0, 0.0)) == pytest.approx(0.2)   # two columns right
    assert overlap_share(a, b, (2.0, 0.0, 0.0)) == 0.0
    assert overlap_share(a, Footprint(GridMap(np.full((10, 10), np.nan), 0.1)), (0.0, 0.0, 0.0)) == 0.0


def test_loop_search_searches_candidates_beyond_the_basin(simulated):
    """With ``loop_search`` every candidate whose drift bound exceeds it is matched after a
    windowed search (issue 13), the window as documented, and the run still recovers the truth."""
    from taichi_match.slam import LOOP_SEARCH_ARM, LOOP_SEARCH_MAX

    result = Slam(SlamOptions(loop_search=0.5)).run(simulated.log)
    searched = [loop for loop in result.loops if loop["window"] is not None]
    assert searched and all(loop["hypotheses"] for loop in searched)
    assert all(loop["window"][0] <= LOOP_SEARCH_MAX and loop["window"][1] == loop["window"][0] / LOOP_SEARCH_ARM
               for loop in searched)
    assert all(not loop["hypotheses"] for loop in result.loops if loop["window"] is None)
    errors = result.poses[:, :2] - simulated.truth[:, :2]
    assert np.sqrt((errors ** 2).sum(axis=1).mean()) < 0.1
    for bad in (-1.0, float("nan"), "1"):
        with pytest.raises(InvalidOptionError):
            SlamOptions(loop_search=bad)


def test_loop_ties_by_hand():
    """Frames at 0-100 m of travel (key = metres), closures 10-50, 52-90 and 91-30: from 51 to 11,
    1 + 1 m through one closure; 90 to 10, 2 m through two; 31 to 11, 1 + 1 + 2 + 1 m through
    three; 70 to 30, 18 + 1 m through two (not the 40 m along the trajectory); without closures,
    the travel between them."""
    from taichi_match.slam import tie_distances

    travelled = np.arange(101.0)
    edges = [{"frames": (10, 50)}, {"frames": (52, 90)}, {"frames": (91, 30)}]
    assert tie_distances(51, [11, 90, 100], [], travelled) == pytest.approx([40.0, 39.0, 49.0])
    assert tie_distances(51, [11], edges, travelled) == pytest.approx([2.0])
    assert tie_distances(90, [10], edges, travelled) == pytest.approx([2.0])
    assert tie_distances(31, [11, 50], edges, travelled) == pytest.approx([5.0, 4.0])
    assert tie_distances(70, [30], edges, travelled) == pytest.approx([19.0])     # 70 -> 52 | 90 -> 91 | 30


def test_loop_ties_against_all_pairs_shortest_paths():
    """tie_distances against a plain oracle on random closures: every pair of frames joined by the
    travel between them, each closure by 0, all shortest paths at once (Floyd-Warshall, dense)."""
    from taichi_match.slam import tie_distances

    rng = np.random.default_rng(5)
    for _ in range(20):
        travelled = np.sort(rng.uniform(0, 60, 40))
        pairs = rng.choice(40, size=(int(rng.integers(0, 12)), 2))
        edges = [{"frames": (int(a), int(b))} for a, b in pairs if a != b]
        dense = np.abs(travelled[:, None] - travelled[None, :])
        for e in edges:
            dense[e["frames"]] = dense[e["frames"][::-1]] = 0.0
        oracle = np.full((40, 40), np.inf)
        np.fill_diagonal(oracle, 0.0)
        oracle = np.minimum(oracle, dense)
        for k in range(40):
            oracle = np.minimum(oracle, oracle[:, k:k + 1] + oracle[k:k + 1, :])
        source = int(rng.integers(40))
        targets = rng.choice(40, 6, replace=False)
        assert tie_distances(source, targets, edges, travelled) == pytest.approx(oracle[source, targets], abs=1e-9)


@pytest.mark.parametrize("overrides", [dict(loop_ties=-1.0), dict(loop_ties=math.inf), dict(loop_ties="5"),
                                       dict(loop_ties=5.0, workers=1), dict(solver="lm"), dict(solver=None)])
def test_loop_ties_options_are_checked(overrides):
    with pytest.raises(InvalidOptionError):
        SlamOptions(**overrides)


def test_loop_ties_match_fewer_candidates_and_keep_the_targets(simulated, mapped):
    """With ``loop_ties`` the run twice round the simulated building matches fewer loop-closure
    candidates than the default run, counts those it leaves, and still meets the ATE targets
    against the exact truth."""
    tied = Slam(loop_ties=5.0).run(simulated.log)
    assert tied.loops_tied > 0 and len(tied.loops) < len(mapped.loops), (tied.loops_tied, len(tied.loops))
    assert mapped.loops_tied == 0
    errors = trajectory_errors(tied.poses, simulated.truth)
    odometry = trajectory_errors(simulated.log.poses, simulated.truth)
    assert errors["ate_m"] <= 0.10 and errors["ate_deg"] <= 1.0 and errors["ate_m"] * 10 <= odometry["ate_m"], errors


def test_isam2_solver_meets_the_targets(simulated):
    """With the incremental solver the run twice round the simulated building still meets the
    ATE targets against the exact truth and beats the odometry tenfold."""
    result = Slam(solver="isam2").run(simulated.log)
    errors = trajectory_errors(result.poses, simulated.truth)
    odometry = trajectory_errors(simulated.log.poses, simulated.truth)
    assert errors["ate_m"] <= 0.10 and errors["ate_deg"] <= 1.0 and errors["ate_m"] * 10 <= odometry["ate_m"], errors


def test_submaps_free_margin_removes_the_front_ends_forward_bias(simulated):
    """A lone scan matched against the 7 scans before it, all cast at the simulated truth, from
    the truth: with the submaps' beams free up to their returns the scans come out ahead of the
    truth (a wall's near side is cleared by the other scans' longer beams: 4.8 mm, mean of 193);
    with the default free margin the mean forward error is under half of that (1.4 mm;
    bench/FRONT_END_BIAS.md, every third scan: 3.6 and -0.9 mm)."""
    from taichi_match import compose, inverse
    from taichi_match.scans import BeamCounts, SensorModel, scans_to_grid
    from taichi_match.slam import SCAN_MODEL, scan_accepted

    options = SlamOptions()
    matcher = Matcher(options.scan_matcher)
    evidence = options.scan_matcher.evidence
    log, truth = simulated.log, simulated.truth

    def mean_forward(margin):
        forward = []
        for k in range(7, len(log.scans)):
            origin = inverse(truth[k - 7])
            counts = BeamCounts(model=SensorModel(max_ray_length=options.max_ray_length, free_margin=margin))
            counts.add([log.scans[j] for j in range(k - 7, k)], np.array([compose(origin, truth[j])
                                                                          for j in range(k - 7, k)]))
            scan = scans_to_grid([log.scans[k]], np.zeros((1, 3)), model=SCAN_MODEL, evidence=evidence)
            pose = compose(origin, truth[k])
            result = matcher.match(counts.grid(evidence=evidence), scan, pose)
            if scan_accepted(result):
                forward.append(compose(inverse(pose), result.pose)[0])
        assert len(forward) >= 150
        return float(np.mean(forward))

    cut, uncut = mean_forward(options.free_margin), mean_forward(0.0)
    assert uncut > 0.003 and abs(cut) < uncut / 2, (cut, uncut)


def test_scans_added_one_at_a_time_map_as_the_robot_goes(simulated, mapped):
    """``Slam.add`` per scan, then ``finish``: the run of the whole log, bit for bit. Each scan's
    pose as returned when it came (before later loop closures moved it) tracks the truth far
    better than the odometry (the simulated truth: an independent source), and ``poses`` shows
    the estimates of the scans so far."""
    slam = Slam()
    live = []
    for k, scan in enumerate(simulated.log.scans):
        live.append(slam.add(scan))
        if k == 50:
            now = slam.poses
            assert now.shape == (51, 3) and np.array_equal(now[-1], live[-1])
    result = slam.finish()
    assert np.array_equal(result.poses, mapped.poses) and np.array_equal(result.frames, mapped.frames)
    assert np.array_equal(result.map.prob, mapped.map.prob, equal_nan=True)
    assert len(result.add_seconds) == len(simulated.log) and np.all(result.add_seconds > 0)
    online = trajectory_errors(np.array(live), simulated.truth)
    odometry = trajectory_errors(simulated.log.poses, simulated.truth)
    assert online["ate_m"] <= odometry["ate_m"] / 3, (online, odometry)
    assert slam.poses.shape == (0, 3)                     # finished: ready for another run


def test_a_refused_scan_leaves_the_run_as_it_was(short_run):
    """A scan ``add`` refuses (InvalidOptionError) changes nothing: the run then goes on as if it
    never came (the same bits as a fresh mapper given only the good scans)."""
    scans = short_run.log.scans
    reference = Slam().run(short_run.log)
    slam = Slam()
    for k, scan in enumerate(scans):
        if k == 9:
            bad = [dataclasses.replace(scan, pose=np.array([np.nan, 0.0, 0.0])),
                   dataclasses.replace(scan, pose=np.zeros(2)),
                   dataclasses.replace(scan, ranges=scan.ranges[:-1]),
                   dataclasses.replace(scan, ranges=np.array(["a"] * len(scan.ranges))),
                   dataclasses.replace(scan, timestamp=scans[k - 1].timestamp),
                   dataclasses.replace(scan, timestamp=float("nan")),
                   dataclasses.replace(scan, max_range=-1.0),
                   dataclasses.replace(scan, pose=scan.pose + np.array([100.0, 0.0, 0.0])),
                   dataclasses.replace(scan, pose=np.array([-1.7e308, 0.0, 0.0])),
                   dataclasses.replace(scan, pose=scan.pose + np.array([0.0, 0.0, 2e3])),
                   dataclasses.replace(scan, angles=np.where(np.arange(len(scan.angles)) == 5, np.nan, scan.angles)),
                   dataclasses.replace(scan, ranges=scan.ranges.astype(complex)),
                   dataclasses.replace(scan, max_range=10**400),
                   dataclasses.replace(scan, max_range=True),
                   dataclasses.replace(scan, timestamp=10**400),
                   dataclasses.replace(scan, timestamp=None),
                   dataclasses.replace(scan, max_range=complex(20.0, 0.0)),
                   "a scan"]
            for wrong in bad:
                with pytest.raises(InvalidOptionError):
                    slam.add(wrong)
            assert len(slam.poses) == 9
        slam.add(scan)
    result = slam.finish()
    assert np.array_equal(result.poses, reference.poses)


@pytest.mark.parametrize("frames", [False, True])
def test_add_then_finish_gives_the_bits_of_run(short_run, frames):
    """Scan by scan (``add``, ``finish``) is the same run as the whole log at once (``run``), with
    submap frames (graph keys 2**30 + i, which need no knowledge of the log's length) or without."""
    reference = Slam(submap_frames=frames).run(short_run.log)
    slam = Slam(submap_frames=frames)
    for scan in short_run.log.scans:
        slam.add(scan)
    result = slam.finish()
    assert result.poses.tobytes() == reference.poses.tobytes()
    assert result.frames.tobytes() == reference.frames.tobytes()
    assert sorted(result.values.keys()) == sorted(reference.values.keys())
    assert any(key >= 2**30 for key in result.values.keys()) == frames


def test_finish_needs_a_usable_scan(short_run):
    slam = Slam()
    with pytest.raises(InvalidOptionError, match="no scan was added"):
        slam.finish()
    blind = dataclasses.replace(short_run.log.scans[0], ranges=np.full(len(short_run.log.scans[0].ranges), np.nan))
    slam.add(blind)
    with pytest.raises(InvalidOptionError, match="no usable beam"):
        slam.finish()
    slam.add(short_run.log.scans[1])                # the refused finish kept the run
    assert len(slam.finish().poses) == 2
    # one scan: its odometry pose, its map
    slam.add(short_run.log.scans[0])
    one = slam.finish()
    assert np.array_equal(one.poses, short_run.log.poses[:1]) and np.isfinite(one.map.prob).any()


def test_the_map_so_far_is_the_scans_so_far_at_their_estimates(short_run):
    """``current_map`` mid-run: the scans added so far cast at ``poses`` (``scans_to_grid``, the
    caster the final map uses, given the estimates independently)."""
    from taichi_match.scans import SensorModel, scans_to_grid

    slam = Slam()
    with pytest.raises(InvalidOptionError, match="no usable scan"):
        slam.current_map()
    for scan in short_run.log.scans[:25]:
        slam.add(scan)
    model = SensorModel(max_ray_length=slam.options.max_ray_length, free_margin=slam.options.free_margin)
    expected = scans_to_grid(short_run.log.scans[:25], slam.poses, resolution=slam.options.resolution, model=model)
    now = slam.current_map()
    assert now.shape == expected.shape and np.array_equal(now.prob, expected.prob, equal_nan=True)
    assert np.isfinite(now.prob).sum() > 1000


def test_an_error_part_way_through_a_scan_breaks_the_run_loudly(short_run):
    """An error inside ``add`` after the scan was taken (here the front end's matcher failing
    once) leaves a run that cannot be trusted: every later ``add``, ``current_map`` and ``finish``
    says so (SlamRunError) until ``close``, after which the mapper maps anew, the same bits as a
    fresh one."""
    from taichi_match import SlamRunError

    scans = short_run.log.scans
    slam = Slam()
    match = slam._scan_matcher.match
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 5:
            raise RuntimeError("the matcher failed")
        return match(*args, **kwargs)

    slam._scan_matcher.match = failing
    for scan in scans[:5]:
        slam.add(scan)
    with pytest.raises(RuntimeError, match="matcher failed"):
        slam.add(scans[5])
    for broken in (lambda: slam.add(scans[6]), slam.finish, slam.current_map,
                   lambda: slam.run(short_run.log)):
        with pytest.raises(SlamRunError):
            broken()
    slam.close()
    slam._scan_matcher.match = match
    assert np.array_equal(slam.run(short_run.log).poses, Slam().run(short_run.log).poses)


def test_run_checks_every_scan_before_mapping_and_add_copies_the_scan(short_run):
    scans = list(short_run.log.scans)
    for k, bad in ((len(scans) - 1, dataclasses.replace(scans[-1], max_range="20")),
                   (3, dataclasses.replace(scans[3], pose=np.zeros(2))),
                   (2, None)):
        steps = []
        with pytest.raises(InvalidOptionError, match=f"scan {k}"):
            Slam().run(LaserLog(tuple(scans[:k] + [bad] + scans[k + 1:]), short_run.log.odometry),
                       progress=lambda i, n: steps.append(i))
        assert steps == []
    with pytest.raises(InvalidOptionError, match="LaserLog"):
        Slam().run(list(scans))
    # a driver that reuses its buffers does not change the run
    reference = Slam().run(short_run.log)
    slam = Slam()
    for scan in scans:
        mine = dataclasses.replace(scan, ranges=scan.ranges.copy(), pose=scan.pose.copy())
        slam.add(mine)
        mine.ranges[:] *= 0.5
        mine.pose[:] = 0.0
    assert np.array_equal(slam.finish().poses, reference.poses)


def test_finish_refuses_without_losing_the_run_and_run_waits_for_it(short_run):
    from taichi_match import SlamRunError

    scans = short_run.log.scans
    slam = Slam()
    still = [dataclasses.replace(s, pose=scans[0].pose) for s in scans[:3]]
    for scan in still:
        slam.add(scan)
    with pytest.raises(InvalidOptionError, match="no odometry"):
        slam.finish()
    with pytest.raises(SlamRunError, match="under way"):
        slam.run(short_run.log)
    for scan in scans[3:]:                           # the run goes on
        slam.add(scan)
    result = slam.finish()
    assert len(result.poses) == len(scans)


def test_the_readme_scan_by_scan_example_runs(tmp_path, monkeypatch):
    """The README's Python block for the loop scan by scan, run as written (in a scratch folder),
    and its outputs loaded back."""
    import re
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = next(b for b in re.findall(r"```python\n(.*?)```", readme, re.S) if "mapper.add" in b)
    monkeypatch.chdir(tmp_path)
    exec(compile(block, "README.md", "exec"), {})
    _, poses = read_tum(tmp_path / "slam_out" / "trajectory.tum")
    assert len(poses) == len(simulate_log(0).log)


def test_scan_times_set_the_first_match_apart():
    from types import SimpleNamespace

    from taichi_match.slam import scan_times

    text = scan_times(SimpleNamespace(add_seconds=np.array([0.001, 0.5, 0.010, 0.020, 0.030])))
    assert "median 20.0 ms" in text and "at most 30 ms" in text and "new process: 500 ms" in text


def test_gate_inflation_widens_the_odometry_gate(short_run):
    """The gate takes ``gate_inflation`` times the match's covariance: made huge, every match the
    verdict accepted passes it (an edge for each); at the default none passes it that the verdict
    refused."""
    wide = Slam(gate_inflation=1e6).run(short_run.log)
    assert all(record["edge"] == record["accepted"] for record in wide.scans)
    default = Slam().run(short_run.log)
    assert all(record["accepted"] or not record["edge"] for record in default.scans)


@pytest.mark.parametrize("overrides", [
    dict(front_end_inflation=1e308), dict(front_end_inflation=1e-308), dict(gate_inflation=float("nan")),
    dict(robust_kernel=1e9), dict(odometry_sd=(1e155, 0, 0, 1e-3, 1e-3)), dict(odometry_sd=(0, 0, 0, 1e-320, 1e-3)),
    dict(odometry_sd="abcde"), dict(odometry_sd=(0.1, 0.1)), dict(scan_matcher="x"), dict(matcher=None),
    dict(loop_ties=True), dict(loop_search=True), dict(bogus=1)])
def test_options_that_would_overflow_the_graph_or_mean_nothing_are_refused(overrides):
    # a red-team pass (2026-12-07): 1e308 and 1e-308 passed "finite and > 0" and wrote NaN and inf
    # information matrices into graph.g2o; an odometry sd of 1e155 overflowed when squared; the rest
    # escaped as TypeError, ValueError or OverflowError
    with pytest.raises(InvalidOptionError):
        Slam(**overrides)
    with pytest.raises(InvalidOptionError):
        Slam("not options")


def test_graph_g2o_cut_short_is_an_error_and_the_old_outputs_stay(short_run, tmp_path, monkeypatch):
    # gtsam's writer reports no error: a full disk or a file size limit cut graph.g2o short and the
    # run ended well; now the file is checked (a line per node and edge) before anything is moved
    result = Slam().run(short_run.log)
    paths = write_outputs(result, tmp_path / "out")
    before = {name: path.read_bytes() for name, path in paths.items()}
    writer = gtsam.writeG2o

    def cut(graph, values, name):
        writer(graph, values, name)
        with open(name, "r+b") as f:
            f.truncate(f.seek(0, 2) // 2)

    monkeypatch.setattr(gtsam, "writeG2o", cut)
    with pytest.raises(OSError, match="in part"):
        write_outputs(result, tmp_path / "out", force=True)
    assert {name: path.read_bytes() for name, path in paths.items()} == before
    assert not [p for p in (tmp_path / "out").iterdir() if p.name.startswith(".slam-")]


def test_output_folders_refused_before_any_work(short_run, tmp_path):
    from taichi_match._slam_outputs import output_paths

    (tmp_path / "file").write_text("x")
    with pytest.raises(NotADirectoryError):
        output_paths(tmp_path / "file" / "sub")                   # its parent is a file
    with pytest.raises(InvalidOptionError, match="UTF-8"):
        output_paths(os.fsdecode(bytes(tmp_path) + b"/out\xffdir"))   # gtsam's writer takes UTF-8 paths only
    for folder in (None, 5):
        with pytest.raises(InvalidOptionError):
            output_paths(folder)
    with pytest.raises(InvalidOptionError):
        write_outputs(None, tmp_path / "out")


def test_a_log_name_that_is_not_utf8_is_written_escaped(short_run, tmp_path):
    result = Slam().run(short_run.log)
    paths = write_outputs(result, tmp_path / "out", source=os.fsdecode(b"runs/bad\xffname.log"))
    assert "bad\\udcffname.log" in paths["report"].read_text(encoding="utf-8")


def test_a_terminating_signal_while_the_outputs_are_staged_removes_the_staging(tmp_path):
    # SIGTERM's default ends the process at once: the temporary folder stayed behind. Within
    # ``_signals_raised`` it is an exception, the cleanups run, then the signal ends the process
    script = ("import os, signal, pathlib\n"
              "from taichi_match.io import _signals_raised\n"
              f"marker = pathlib.Path({str(tmp_path / 'cleaned')!r})\n"
              "with _signals_raised():\n"
              "    try:\n"
              "        os.kill(os.getpid(), signal.SIGTERM)\n"
              "        signal.pause()\n"
              "    finally:\n"
              "        marker.write_text('yes')\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=60)
    assert done.returncode == -signal.SIGTERM and (tmp_path / "cleaned").read_text() == "yes"
    assert b"Traceback" not in done.stderr


def test_candidates_with_few_walls_at_the_guess_are_not_matched(simulated, mapped, monkeypatch):
    """Loop-closure candidates whose submaps' walls at the guess meet fewer than ``LOOP_MIN_WALLS``
    known cells of the other are not matched (and counted); on the simulated run those would all
    have been turned down: matching every candidate gives the same poses, bit for bit, and more
    closures tried, none of the extra ones accepted."""
    import taichi_match.slam as slam_module

    assert mapped.loops_few_walls > 0
    assert f"too few walls at the guess: {mapped.loops_few_walls}" in slam_module.report(mapped)
    monkeypatch.setattr(slam_module, "LOOP_MIN_WALLS", 0)
    every = Slam().run(simulated.log)
    assert every.loops_few_walls == 0
    assert len(every.loops) == len(mapped.loops) + mapped.loops_few_walls
    assert sum(lp["accepted"] for lp in every.loops) == sum(lp["accepted"] for lp in mapped.loops)
    np.testing.assert_array_equal(every.poses, mapped.poses)


def test_the_audit_compares_every_pair_as_compare_walls_does(simulated, mapped, monkeypatch):
    """The audit's lookups, made per grid for all its pairs at once, give each pair the walls
    compared, agreement and conflict that ``compare_walls`` gives the pair alone: with thresholds
    that let every pair through, the audit lists exactly the pairs a plain loop over
    ``compare_walls`` finds with walls compared, with the same figures."""
    import taichi_match.slam as slam_module
    from taichi_match._verdict import compare_walls, placed_walls

    monkeypatch.setattr(slam_module, "DISAGREE_AGREEMENT", 2.0)
    monkeypatch.setattr(slam_module, "DISAGREE_CONFLICT", -1.0)
    monkeypatch.setattr(slam_module, "MIN_WALLS", 1)
    seen = {}
    original = Slam.audit

    def keeping(self, scans, submaps, est):
        out = original(self, scans, submaps, est)
        usable = [sub for sub in submaps if sub.final_grid is not None]
        walls = {sub.index: self._matcher.prepare(sub.final_grid, levels=1).wall_distance for sub in usable}
        plain = []
        for j, b in enumerate(usable):
            for a in usable[:j]:
                if set(a.scans) & set(b.scans):
                    continue
                wa, wb = walls[a.index], walls[b.index]
                compared, agreement, conflict = compare_walls(
                    wa, wb, placed_walls(wa, wb, compose(inverse(est[a.key]), est[b.key])))
                if compared:
                    plain.append(((a.index, b.index), compared, agreement, conflict))
        seen["audit"] = [(p["submaps"], p["walls"], p["agreement"], p["conflict"]) for p in out]
        seen["plain"] = plain
        return out

    monkeypatch.setattr(Slam, "audit", keeping)
    Slam(audit="report", loop_gate=None).run(simulated.log)
    assert len(seen["plain"]) >= 100
    assert seen["audit"] == seen["plain"]
