"""Real-time figures (issue 5): one command, every figure, written to bench/RESULTS.md.

    python bench/realtime.py                       # full run (the memory check takes minutes)
    python bench/realtime.py --quick               # fewer trials, 1,000 matches for memory

Figures, each against the targets of the real-time issue:
- the paper's corridor from Table 1's wide initial poses: median and 95th percentile of a full
  match (covariance included), the speed-up over the same algorithm on the NumPy baseline in the
  same run, and the Table 1 success rate;
- real-map pairs (bench/real_maps.py's protocol): median time and success;
- the kernel: ns per cell-pose of a 13-pose launch, against a gather-only kernel over the same
  cells and poses (what this CPU can do: the index arithmetic with its clamp, one gather and an
  add per cell-pose, without reading B or masking);
- a fresh process: import, initialisation and the first match, with Taichi's offline cache warm
  and cold;
- scaling with map size (120^2 to 1920^2 cells) and with the share of known cells;
- throughput of one matcher over 100 different pairs;
- resident memory over many matches in one process.
"""

import argparse
import datetime
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import taichi_match as tm
from taichi_match.reproduce import git_revision
from taichi_match._cost import affine_coefficients, gradient_stencil
from taichi_match._kernels import _LOCK, _import_taichi, ensure_initialized
from taichi_match.scenes import corridor, noisy_copy

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import real_maps  # noqa: E402  (the real-map protocol)
from bench_match import median_time  # noqa: E402


def rss_mb():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def corridor_figures(trials, numpy_trials, seed=0):
    grid = corridor()
    fast, slow = tm.Matcher(), tm.Matcher(engine="numpy")
    fast.match(grid, grid, (0.1, 0.1, 0.0))
    r0s = np.random.default_rng(seed).uniform(-1, 1, (trials, 3)) * (1.5, 1.5, 0.38)
    ours, base = [], []
    for k, r0 in enumerate(r0s):
        ours.append(fast.match(grid, grid, r0))
        if k < numpy_trials:
            base.append(slow.match(grid, grid, r0))
    t = np.array([r.seconds for r in ours])
    ok = np.mean([abs(r.pose[1]) < 0.025 and abs(r.pose[2]) < 0.045 for r in ours]) * 100
    ratio = np.median([r.seconds for r in base]) / np.median(t[:numpy_trials])
    return {"median_ms": 1e3 * np.median(t), "p95_ms": 1e3 * np.percentile(t, 95), "speedup": ratio,
            "success": ok, "trials": trials, "numpy_trials": numpy_trials}


def real_map_figures(pairs_per_map, seed=0):
    rng = np.random.default_rng(seed)
    matcher = tm.Matcher()
    times, ok = [], []
    for grid in real_maps.load_maps().values():
        for a, b, truth in real_maps.make_pairs(grid, pairs_per_map, rng):
            for _ in range(3):            # three guesses per pair: the first also blurs the new maps
                r0 = truth + np.concatenate([rng.uniform(-0.5, 0.5, 2), rng.uniform(-0.2, 0.2, 1)])
                res = matcher.match(a, b, r0)
                e_t, e_r = real_maps.errors(res.pose, truth)
                times.append(res.seconds)
                ok.append(e_t < 2 * grid.resolution and e_r < np.radians(1.0))
    return {"median_ms": 1e3 * np.median(times), "success": 100 * np.mean(ok), "matches": len(times)}


def kernel_figures(repeats=101):
    """ns per cell-pose of the 13-pose discrepancy launch and of a gather-only kernel."""
    ti = _import_taichi()
    kernel = ensure_initialized()
    prepared = tm.Matcher().prepare(corridor())

    @ti.kernel
    def gather_only(a: ti.types.ndarray(dtype=ti.f32, ndim=2), rows: ti.types.ndarray(dtype=ti.i32, ndim=2),
                    affine: ti.types.ndarray(dtype=ti.f64, ndim=2), out: ti.types.ndarray(dtype=ti.f32, ndim=2)):
        # the least a cell-pose needs: its clamped index in A and one gather, summed; no B, no masks
        u_max, v_max = a.shape[1] - 1, a.shape[0] - 1
        for k, r in ti.ndrange(affine.shape[0], rows.shape[0]):
            i = rows[r, 0]
            du, dv = ti.f32(affine[k, 0]), ti.f32(affine[k, 3])
            u0 = ti.f32(affine[k, 1] * i + affine[k, 2])
            v0 = ti.f32(affine[k, 4] * i + affine[k, 5])
            acc = ti.f32(0.0)
            for j in range(rows[r, 1], rows[r, 2]):
                iu = ti.min(ti.max(ti.cast(u0 + du * j, ti.i32), 0), u_max)
                iv = ti.min(ti.max(ti.cast(v0 + dv * j, ti.i32), 0), v_max)
                acc += a[iv, iu]
            out[k, r] = acc

    affine = affine_coefficients(gradient_stencil(np.array([0.3, 0.2, 0.05]), np.full(3, 0.01)),
                                 prepared.blurred, prepared.blurred)
    n_rows = prepared.rows.shape[0]
    out = np.empty((1, 13, n_rows), np.float32)
    gout = np.empty((13, n_rows), np.float32)
    cells = int((prepared.rows[:, 2] - prepared.rows[:, 1]).sum())

    def timed(fn):
        fn()                                      # warm-up
        return median_time(fn, repeats)

    with _LOCK:
        t_kernel = timed(lambda: kernel(prepared.padded, prepared.values, prepared.rows, affine, out, 0))
        t_gather = timed(lambda: gather_only(prepared.padded, prepared.rows, affine, gout))
    per = 13 * cells
    return {"kernel_ns": 1e9 * t_kernel / per, "gather_ns": 1e9 * t_gather / per,
            "ratio": t_kernel / t_gather, "cell_poses": per, "kernel_ms": 1e3 * t_kernel}


FRESH = ("import time; t0 = time.perf_counter(); import taichi_match as tm; "
         "from taichi_match.scenes import corridor; g = corridor(); tm.match(g, g, (0.3, 0.2, 0.1)); "
         "print(time.perf_counter() - t0)")


def fresh_process_figures():
    def run(env):
        t0 = time.perf_counter()
        out = subprocess.run([sys.executable, "-c", FRESH], capture_output=True, text=True, env=env, timeout=300)
        wall = time.perf_counter() - t0
        return wall, float(out.stdout.strip() or "nan")

    env = dict(os.environ)
    run(env)                                                   # make sure the default cache is warm
    warm = run(env)
    with tempfile.TemporaryDirectory() as cache:
        cold = run(dict(env, TI_OFFLINE_CACHE_FILE_PATH=cache))
    return {"warm_s": warm[0], "warm_inside_s": warm[1], "cold_s": cold[0], "cold_inside_s": cold[1]}


def scaling_figures(trials=5):
    """Time per match against map size (the corridor drawn at finer cells) and known share."""
    matcher = tm.Matcher()
    r0s = np.random.default_rng(3).uniform(-1, 1, (trials, 3)) * (0.5, 0.5, 0.2)
    size_rows = []
    for n in (120, 240, 480, 960, 1920):
        grid = corridor(resolution=12.0 / n, wall=max(0.05, 2 * 12.0 / n))
        matcher.match(grid, grid, r0s[0])
        t = [matcher.match(grid, grid, r0).seconds for r0 in r0s]
        size_rows.append((n, int(grid.known.sum()), 1e3 * np.median(t)))
    share_rows = []
    base = corridor()
    for width in (1.5, 3.0, 6.0, 9.0, 11.0):
        grid = corridor(width=width)
        matcher.match(grid, grid, r0s[0])
        t = [matcher.match(grid, grid, r0).seconds for r0 in r0s]
        share_rows.append((width, float(grid.known.mean()), int(grid.known.sum()), 1e3 * np.median(t)))
    del base
    return size_rows, share_rows


def throughput_figures(pairs=100):
    grid = corridor()
    rng = np.random.default_rng(5)
    maps = [noisy_copy(grid, flip=0.001, drop=0.05, rng=rng) for _ in range(pairs)]
    r0s = rng.uniform(-1, 1, (pairs, 3)) * (0.5, 0.5, 0.2)
    matcher = tm.Matcher()
    matcher.match(grid, maps[0], r0s[0])
    t0 = time.perf_counter()
    for b, r0 in zip(maps, r0s):
        matcher.match(grid, b, r0)
    wall = time.perf_counter() - t0
    return {"pairs": pairs, "per_second": pairs / wall, "wall_s": wall}


def memory_figures(matches):
    grid = corridor(size=6.0)
    matcher = tm.Matcher()
    rng = np.random.default_rng(6)
    r0s = rng.uniform(-1, 1, (matches, 3)) * (0.3, 0.3, 0.1)
    samples = []
    for k, r0 in enumerate(r0s):
        matcher.match(grid, grid, r0)
        if k in (matches // 10, matches - 1):
            samples.append(rss_mb())
    return {"matches": matches, "rss_after_10pct_mb": samples[0], "rss_end_mb": samples[-1],
            "growth_pct": 100 * (samples[-1] / samples[0] - 1)}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", default=str(HERE / "RESULTS.md"))
    args = parser.parse_args()
    q = args.quick
    lines = ["# Real-time figures", "",
             f"`python bench/realtime.py{' --quick' if q else ''}` at revision {git_revision()} on "
             f"{datetime.date.today()}: {platform.machine()}, {os.cpu_count()} cores, Python "
             f"{platform.python_version()}. Targets from the real-time issue in the last column.", ""]

    def emit(text=""):
        print(text, flush=True)
        lines.append(text)

    c = corridor_figures(30 if q else 100, 5 if q else 10)
    emit("| corridor (Table 1 wide row) | value | target |")
    emit("|---|---|---|")
    emit(f"| median full match | {c['median_ms']:.1f} ms | <= 5 ms |")
    emit(f"| 95th percentile | {c['p95_ms']:.1f} ms | <= 10 ms |")
    emit(f"| speed-up over NumPy, same run ({c['numpy_trials']} shared trials) | {c['speedup']:.0f}x | >= 500x |")
    emit(f"| Table 1 success ({c['trials']} trials) | {c['success']:.0f} % | 98 % |")
    r = real_map_figures(2 if q else 8)
    emit(f"| real-map pairs: median per match ({r['matches']} matches) | {r['median_ms']:.1f} ms | <= 10 ms |")
    emit(f"| real-map pairs: success | {r['success']:.1f} % | unchanged (>= 95 %) |")
    k = kernel_figures()
    emit(f"| kernel: 13-pose launch | {k['kernel_ms']:.2f} ms, {k['kernel_ns']:.3f} ns per cell-pose | |")
    emit(f"| gather-only kernel, same cells | {k['gather_ns']:.3f} ns per cell-pose | |")
    emit(f"| kernel / gather bound | {k['ratio']:.1f}x | <= 2x |")
    f = fresh_process_figures()
    emit(f"| fresh process, warm cache: import + init + first match | {f['warm_s']:.2f} s "
         f"(inside Python {f['warm_inside_s']:.2f} s) | <= 1.5 s |")
    emit(f"| fresh process, cold cache | {f['cold_s']:.2f} s (inside Python {f['cold_inside_s']:.2f} s) | report |")
    t = throughput_figures(100)
    emit(f"| throughput, one matcher, {t['pairs']} different pairs | {t['per_second']:.1f} matches/s | report |")
    m = memory_figures(1000 if q else 10000)
    emit(f"| resident memory over {m['matches']} matches | {m['rss_after_10pct_mb']:.0f} -> {m['rss_end_mb']:.0f} MB "
         f"({m['growth_pct']:+.1f} %) | within 5 % |")
    emit()
    sizes, shares = scaling_figures(3 if q else 5)
    emit("| map cells | known cells | median ms per match |")
    emit("|---|---|---|")
    for n, known, ms in sizes:
        emit(f"| {n}^2 | {known} | {ms:.1f} |")
    emit()
    emit("| corridor width m (480^2 map) | known share | known cells | median ms per match |")
    emit("|---|---|---|---|")
    for width, share, known, ms in shares:
        emit(f"| {width:g} | {share:.2f} | {known} | {ms:.1f} |")
    try:
        from taichi_match.plots import _plt
        plt = _plt()
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.loglog([s[1] for s in sizes], [s[2] for s in sizes], "o-", label="map size (120^2 .. 1920^2)")
        ax.loglog([s[2] for s in shares], [s[3] for s in shares], "s-", label="known share (480^2)")
        ax.set_xlabel("known cells")
        ax.set_ylabel("median ms per match")
        ax.legend()
        fig.tight_layout()
        fig.savefig(HERE / "scaling.png", dpi=90)
        plt.close(fig)
        emit()
        emit("![scaling](scaling.png)")
    except ImportError:
        pass
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
