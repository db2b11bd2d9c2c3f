"""iSAM2 update cost against the number of poses, in whichever gtsam this interpreter has.

Run by scripts/isam2_gtsam_versions.sh in two throwaway environments (gtsam 4.3.0, the pinned one, and
gtsam 4.2.2, which needs numpy < 2 and so cannot be installed beside objslam's other dependencies) to show
how much of the growth measured by `objslam bench isam2` is gtsam's own.
"""

import sys
import time
from importlib.metadata import version

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X


def chain(n: int) -> tuple[float, float]:
    """Mean ISAM2.update time (ms) of a bare Pose3 odometry chain around 1000 and at the last 200 poses."""
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.1)
    params.relinearizeSkip = 1
    params.enablePartialRelinearizationCheck = True
    params.cacheLinearizedFactors = True
    isam = gtsam.ISAM2(params)
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.01)
    pose, step = gtsam.Pose3(), gtsam.Pose3(gtsam.Rot3.Yaw(0.01), gtsam.Point3(0.1, 0, 0))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), pose, noise))
    values.insert(X(0), pose)
    isam.update(graph, values)
    times = []
    for i in range(1, n):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), step, noise))
        pose = pose.compose(step)
        values.insert(X(i), pose)
        t0 = time.perf_counter()
        isam.update(graph, values)
        times.append(time.perf_counter() - t0)
    ms = np.array(times) * 1e3
    return float(ms[900:1100].mean()), float(ms[-200:].mean())


def service_graph(n: int) -> tuple[float, float, float]:
    """t(1000), t(n) (ms per keyframe) and their ratio for `objslam bench isam2`'s simulation with the whole
    graph in one iSAM2 (the service's graph before the bounded window)."""
    from bench.isam2 import growth, simulate, window_mean
    from graph.settings import GraphSettings

    r = simulate(n, 300, GraphSettings(relinearize_threshold=0.1), windowed=False, seed=0, returns=True)
    ks = r["keyframe_s"]
    return window_mean(ks, 1000) * 1e3, window_mean(ks, n) * 1e3, growth(ks, n, 1000, n)


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 10000
    a, b = chain(n)
    print(f"gtsam {version('gtsam')} numpy {np.__version__}")
    print(f"odometry chain: update {a:.3f} ms around 1000 poses, {b:.3f} ms at {n}: ratio {b / a:.2f}")
    if "--service" in sys.argv:
        small, large, ratio = service_graph(n)
        print(
            f"whole graph in one iSAM2: {small:.2f} ms per keyframe around 1000, {large:.2f} at {n}: ratio {ratio:.2f}"
        )
