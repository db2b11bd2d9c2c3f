"""Write tests/fixtures/state_v0.1.0: a small `serve --state-dir` directory of release 0.1.0 (commit cd63eff).

Run once, on that release, before the packages moved (issue 23): `python scripts/make_state_fixture.py`.
The directory holds the service's final snapshot after FRAMES frames of a small synthetic scene and
``expected.json``: what a service resumed from it must report (frames processed, keyframes, the optimised
trajectory, loop records, object ids), and the scene spec, so a test can replay the frames that follow.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from service.config import load_settings
from service.node import ServiceNode
from service.protocol import encode_frame
from service.replay import frame_publisher
from service.zenoh_session import open_session
from sources import open_dataset

SPEC = "synthetic:room?seed=0&frames=160&fps=10&width=320&height=240"
FRAMES = 150
OUT = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "state_v0.1.0"


def main() -> None:
    shutil.rmtree(OUT, ignore_errors=True)
    OUT.mkdir(parents=True)
    overrides = {
        "state_dir": OUT,
        "ingest": {"queue_size": 1000},
        "detector": {"enabled": False},
        "persistence": {"keep": 2, "every_keyframes": 1000},
    }
    settings = load_settings(None, overrides)
    ds = open_dataset(SPEC)
    session = open_session(settings.zenoh, "server", embedded=True)
    try:
        node = ServiceNode(settings, session)
        node.start()
        pub = frame_publisher(session, f"{node.prefix}/rgbd")
        for i in range(FRAMES):
            pub.put(encode_frame(ds.frame(i)))
        assert node.wait_done(FRAMES, timeout=300.0) and node.queue.dropped == 0
        pub.undeclare()
        node.stop()
        trajectory, _ = node.trajectories()
        status = node.status()
        expected = {
            "spec": SPEC,
            "frames": FRAMES,
            "overrides": {k: v for k, v in overrides.items() if k != "state_dir"},
            "frames_processed": status["frames_processed"],
            "keyframes": status["keyframes"],
            "timestamps": [repr(float(t)) for t in trajectory.timestamps],
            "poses": [[repr(float(v)) for v in T.ravel()] for T in trajectory.poses],
            "loops": [
                {k: r[k] for k in ("query_frame", "match_frame", "accepted", "reason")}
                for r in node.loops_reply()["loops"]
            ],
            "objects": sorted(o["id"] for o in node.objects_reply()["objects"]),
        }
    finally:
        session.close()
    for extra in OUT.iterdir():  # only the snapshot: the outputs are not part of what is resumed
        if extra.name != "snapshots":
            shutil.rmtree(extra) if extra.is_dir() else extra.unlink()
    (OUT / "expected.json").write_text(json.dumps(expected, indent=1) + "\n")
    print(
        f"{OUT}: {expected['frames_processed']} frames, {expected['keyframes']} keyframes, "
        f"{len(expected['loops'])} loop records, {len(expected['objects'])} objects"
    )


if __name__ == "__main__":
    main()
