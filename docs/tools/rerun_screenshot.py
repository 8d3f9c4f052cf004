"""Screenshots of a run's .rrd in the real rerun viewer on a headless machine (docs/hil.md,
"Opening a run's recording in the viewer").

    apt-get install -y mesa-vulkan-drivers        # software Vulkan (lavapipe), once
    .venv/bin/python -m docs.tools.rerun_screenshot RUN.rrd OUT_PREFIX [--at 0.5 0.99] [--size 1600x1000]

Starts the viewer shipped in the rerun-sdk wheel (``--headless``, bound to 127.0.0.1), opens the
recording, moves the ``sim_time`` cursor to each ``--at`` time (s) and writes ``OUT_PREFIX_<k>.png``;
stops the viewer at the end.  The "Software rasterizer" warning of the viewer is expected.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import time


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rrd")
    ap.add_argument("out")
    ap.add_argument("--at", type=float, nargs="*", default=[])
    ap.add_argument("--size", default="1600x1000")
    ap.add_argument("--port", type=int, default=19877)
    a = ap.parse_args(argv)
    import rerun_cli
    from rerun.experimental import ViewerClient
    binary = os.path.join(os.path.dirname(rerun_cli.__file__), "rerun")
    viewer = subprocess.Popen([binary, "--headless", "--bind", "127.0.0.1", "--port", str(a.port),
                               "--hide-welcome-screen", "--window-size", a.size],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        c = None
        for _ in range(200):
            try:
                c = ViewerClient.connect(f"rerun+http://127.0.0.1:{a.port}/proxy")
                c.get_state()
                break
            except Exception:
                c = None
                time.sleep(0.2)
        if c is None:
            raise SystemExit("rerun_screenshot: the viewer did not come up")
        c.open(os.path.abspath(a.rrd))
        time.sleep(4)
        shots = []
        for k, t in enumerate(a.at or [None]):
            if t is not None:
                c.set_time("sim_time", duration=t, play_state="paused")
                time.sleep(2)
            p = os.path.abspath(f"{a.out}_{k}.png")
            c.save_screenshot(p)
            shots.append(p)
            time.sleep(0.5)
        for p in shots:
            print(p)
    finally:
        viewer.terminate()
        viewer.wait(10)


if __name__ == "__main__":
    main()
