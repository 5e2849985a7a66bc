"""The calibrate action's round trip between two hosts vs on one machine (issue 13, target: within
10 %).

Runs the same pipeline in two ways, alternately (``--rounds`` each, so a change in the machine's
load hits both), same scene, bag and parameters (test/netns.py ``start_pipeline``):

- two hosts: vehicle (map_builder, lidar bag_player) and roadside unit (calibrator, camera
  bag_player, action client) in two network namespaces joined by a veth pair, DDS over UDPv4 on
  the link only (docs/two-hosts.md);
- localhost: the same processes on this machine's own network with the project's usual settings
  (localhost discovery, Fast DDS shared memory).

In each, the roadside client waits until the calibrator holds the whole map, sends ``--goals``
calibration goals one after the other (no verification starts) and then ``--refused`` goals the
calibrator answers at once (a negative bound: the action protocol's own round trip, no engine).
Round trip = send goal -> result at the client; "difference" = round trip - the engine's own
seconds (what the ROS side adds). Prints every goal, the medians and the ratios. ``--rate 100``
limits the link to 100 Mbit/s (tc tbf on both veth ends, and a flow controller on the map's
writer) to see what a real link's speed does to the map.
Run it alone (under the shared CPU lock): the figure is CPU-bound and a second job moves it.

    flock /tmp/semcal-heavy.lock .venv/bin/python benchmarks/bench_two_hosts.py --scene SCENE

Without ``--scene`` the demo scene (small junction, seed 0, with its bag) is generated (~10 s).
Needs root for the namespaces.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "test")]

import netns  # noqa: E402

from semcal_tools.launch import DomainLock  # noqa: E402


def run_mode(mode: str, scene: Path, out: Path, goals: int, refused: int, params: dict,
             rate_mbit: float | None = None) -> dict:
    """One pipeline (``two-hosts`` or ``localhost``); the client's report plus link counters.
    ``rate_mbit``: the link limited to that rate (a token bucket with a 200 ms queue on each veth
    end) and the map's writer to 80 % of it (a Fast DDS flow controller)."""
    lock = DomainLock()
    link = netns.VethPair() if mode == "two-hosts" else None
    flow = int(rate_mbit * 1e6 / 8 * 0.8) if rate_mbit and link is not None else None
    hosts = netns.Hosts(link, lock.domain, out, flow_bytes_per_s=flow)
    try:
        if flow:
            for host in link.hosts:
                subprocess.run(host.exec_argv(["tc", "qdisc", "add", "dev", host.ifname, "root",
                                               "tbf", "rate", f"{rate_mbit}mbit", "burst",
                                               "64kb", "latency", "200ms"]), check=True)
        t0 = time.monotonic()
        client, _ = netns.start_pipeline(hosts, scene, out / "client.json", goals=goals,
                                         refused=refused, calibrator_params=params,
                                         timeout=600.0)
        code = client.wait(goals * 600.0 + 300.0)
        report = json.loads((out / "client.json").read_text())
        if code != 0 or "error" in report:
            raise RuntimeError(f"{mode}: client failed: {report.get('error')}\n{hosts.logs()}")
        report["wall"] = time.monotonic() - t0
        if link is not None:
            report["link"] = link.vehicle.counters()
        return report
    finally:
        hosts.close()
        if link is not None:
            link.close()
        lock.release()


def load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, help="scene folder with bag/ (default: generate the "
                                               "demo scene)")
    ap.add_argument("--rounds", type=int, default=2,
                    help="runs per mode, alternating localhost / two hosts (default 2)")
    ap.add_argument("--goals", type=int, default=4, help="calibration goals per run")
    ap.add_argument("--refused", type=int, default=20, help="refused goals per run")
    ap.add_argument("--evaluations", type=int, nargs=3, default=[60, 30, 30],
                    help="engine.schedule.max_evaluations (default 60 30 30, no restarts: a "
                         "short engine run; 0 0 0 = the calibrator's default schedule)")
    ap.add_argument("--rate", type=float, metavar="MBIT",
                    help="limit the link to MBIT Mbit/s (tc tbf, 200 ms queue) and the map's "
                         "writer to 80 %% of it (Fast DDS flow controller); default: the veth's "
                         "full speed, no flow controller")
    ap.add_argument("--out", type=Path, help="folder for logs and reports")
    args = ap.parse_args()

    reason = netns.unavailable_reason()
    if reason:
        print(f"cannot run: {reason}", file=sys.stderr)
        return 1
    netns.remove_stale_namespaces()
    scene = args.scene
    if scene is None:
        from semcal_tools.scenes import SIZES, generate_scene

        scene = Path(tempfile.mkdtemp(prefix="bench-two-hosts-scene-"))
        generate_scene(scene, "junction", 0, "ideal", SIZES["small"], progress=False)
    out = args.out or Path(tempfile.mkdtemp(prefix="bench-two-hosts-"))
    params = ({} if args.evaluations == [0, 0, 0] else
              {"engine.schedule.max_evaluations": args.evaluations,
               "engine.schedule.restarts": [0, 0, 0]})
    print(f"scene {scene}; {args.rounds} runs per mode, each {args.goals} calibration goals + "
          f"{args.refused} refused goals; engine {params or 'default schedule'}; link "
          f"{f'{args.rate:g} Mbit/s' if args.rate else 'unlimited'}; logs in {out}")
    goals: dict[str, list[dict]] = {"localhost": [], "two-hosts": []}
    for r in range(1, args.rounds + 1):
        for mode in goals:
            print(f"--- run {r}, {mode} (load before: {load()})", flush=True)
            rep = run_mode(mode, scene, out / f"{mode}-{r}", args.goals, args.refused, params,
                           args.rate)
            goals[mode] += rep["goals"]
            for i, g in enumerate(rep["goals"], 1):
                if g["kind"] == "calibrate" or i == args.goals + 1:
                    print(f"  goal {i:2d} {g['kind']:9s} {g['status']:9s} round trip "
                          f"{g['round_trip']:7.3f} s, engine {g['server_seconds']:6.3f} s, "
                          f"difference {g['round_trip'] - g['server_seconds']:6.3f} s")
            print(f"  map of {rep['map_points']} points held {rep['map_held_after']:.1f} s after "
                  f"the server was found; whole run {rep['wall']:.1f} s; load after: {load()}")
            if "link" in rep:
                c = rep["link"]
                print(f"  vehicle veth: sent {c['tx_bytes'] / 1e6:.1f} MB in {c['tx_packets']} "
                      f"packets, received {c['rx_bytes'] / 1e6:.1f} MB")
    for mode, gs in goals.items():
        bad = [g for g in gs if g["status"] != ("succeeded" if g["kind"] == "calibrate"
                                                  else "aborted")]
        if bad:
            print(f"{mode}: unexpected outcome: {bad[0]['status']}: {bad[0]['message']}")
            return 1

    def median(mode: str, kind: str, what) -> float:
        return statistics.median(what(g) for g in goals[mode] if g["kind"] == kind)

    print("--- medians over all runs (round trip: send goal -> result at the client; "
          "difference: round trip - the engine's own seconds)")
    rows = [("calibrate", "round trip", lambda g: g["round_trip"]),
            ("calibrate", "engine", lambda g: g["server_seconds"]),
            ("calibrate", "difference", lambda g: g["round_trip"] - g["server_seconds"])]
    if args.refused:
        rows.append(("refused", "round trip", lambda g: g["round_trip"]))
    result = {}
    for kind, name, what in rows:
        local, two = median("localhost", kind, what), median("two-hosts", kind, what)
        result[(kind, name)] = (local, two)
        print(f"{kind:9s} {name:10s}: localhost {local:8.4f} s, two hosts {two:8.4f} s "
              f"({100 * (two / local - 1):+.1f} %)")
    local, two = result[("calibrate", "round trip")]
    print(f"target (calibration round trip within 10 % of localhost): "
          f"{'met' if two <= 1.10 * local else 'MISSED'} ({100 * (two / local - 1):+.1f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
