"""``semcal evaluate``: the paper's evaluation protocol on scene folders (docs/scenes.md)."""

from __future__ import annotations

import argparse
import sys


def _loss_choice(value: str) -> str:
    """``--loss`` checked when evaluate runs, not when the parser is built: the loss package
    imports numba (0.3 s), which every other ``semcal`` command would pay for its ``--help``."""
    from semcal_ros.engine.loss import LOSS_KINDS

    choices = (*LOSS_KINDS, "both", "all")
    if value not in choices:
        raise argparse.ArgumentTypeError(
            f"invalid choice: {value!r} (choose from {', '.join(choices)})")
    return value


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "evaluate", help="the paper's protocol: many noisy starts, keep the lowest-loss runs",
        description="Calibrate from --runs initial guesses (ground truth + uniform noise of "
                    "+-2.5 m in x, y, z and +-5 deg in pitch and yaw), keep the --keep runs of "
                    "lowest loss, report their mean translation and rotation errors, the same "
                    "over all runs, the success rate (< 5 cm and < 0.1 deg) and seconds per run.")
    p.add_argument("scenes", nargs="+", metavar="DIR",
                   help="scene folder(s) from `semcal scene` (with --from-json: JSON files)")
    p.add_argument("--runs", type=int, default=30, help="initial guesses per scene (default 30)")
    p.add_argument("--keep", type=int, default=10, help="lowest-loss runs kept (default 10)")
    p.add_argument("--seed", type=int, default=0, help="seed of the initial guesses (default 0)")
    p.add_argument("--loss", default="l2", type=_loss_choice,
                   help="loss of the registration: a kind of engine.loss.kind (default l2), or "
                        "all (or both) = a column each")
    p.add_argument("--config", help="ROS 2 parameter file of the engine (config/calibrator.yaml)")
    p.add_argument("--label-mapping", help="YAML changing the class alignment")
    p.add_argument("--map", help="map PLY to use instead of DIR/map.ply (relative to DIR unless "
                                 "absolute), e.g. one built by `semcal build-map`")
    p.add_argument("--json", help="write every number (per run and summary) to this JSON file")
    p.add_argument("--overlay", help="PNG/JPG per scene: the map at the lowest-loss pose over "
                                     "image.png ({scene} in the name is replaced by the folder "
                                     "name, {loss} by the loss)")
    p.add_argument("--paper", action="store_true", help="append the paper's Table I rows")
    p.add_argument("--from-json", action="store_true",
                   help="run nothing: print the table of earlier --json outputs given as DIR")
    p.add_argument("--single", action="store_true",
                   help="one schedule per start (no verification starts): the paper's single "
                        "run; default: the engine's full default procedure per start")
    p.add_argument("--label-noise", default="",
                   help="apply a label-noise model to every scene's labels.png first: legacy, "
                        "network or kitti_espnetv2 (docs/quality.md)")
    p.add_argument("--noise-seed", type=int, default=1, help="seed of --label-noise (default 1)")
    p.add_argument("--start-xyz", type=float, default=2.5, metavar="M",
                   help="each start up to this far off the truth per axis (default 2.5 m, the paper)")
    p.add_argument("--start-pitch", type=float, default=5.0, metavar="DEG",
                   help="each start's pitch up to this far off (default 5 deg)")
    p.add_argument("--start-yaw", type=float, default=5.0, metavar="DEG",
                   help="each start's yaw up to this far off (default 5 deg; 180: heading unknown)")
    p.add_argument("--yaw-search", action="store_true",
                   help="search the heading over the full circle first (engine.search.yaw_search)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json
    from dataclasses import asdict
    from pathlib import Path

    from tqdm import tqdm

    from semcal_tools.protocol import ProtocolParams, evaluate_scene, format_table
    from semcal_ros.engine.labels import LabelMapping
    from semcal_ros.engine.params import CalibrationParams

    if args.from_json:
        return _table_from_json([Path(p) for p in args.scenes], args.paper)
    protocol = ProtocolParams(runs=args.runs, keep=args.keep, seed=args.seed,
                              noise_xyz_m=args.start_xyz, noise_pitch_deg=args.start_pitch,
                              noise_yaw_deg=args.start_yaw)
    params = CalibrationParams.from_file(args.config)
    if args.yaw_search:
        from dataclasses import replace

        params = replace(params, search=replace(params.search, yaw_search=True))
    mapping = LabelMapping.from_yaml(args.label_mapping) if args.label_mapping else LabelMapping()
    folders = [Path(s) for s in args.scenes]
    for folder in folders:
        for name in ("labels.png", "camera_info.yaml", "ground_truth.yaml"):
            if not (folder / name).is_file():
                raise FileNotFoundError(f"{folder} is not a scene folder: {name} is missing")
    from semcal_ros.engine.loss import LOSS_KINDS

    losses = tuple(LOSS_KINDS) if args.loss in ("both", "all") else (args.loss,)
    results = []
    bar = tqdm(total=len(folders) * len(losses) * protocol.runs, unit="run", file=sys.stderr,
               disable=args.quiet, dynamic_ncols=True)
    try:
        for folder in folders:
            map_file = None
            if args.map:
                map_file = Path(args.map) if Path(args.map).is_absolute() else folder / args.map
            for loss in losses:
                errors: list[tuple[float, float]] = []

                def on_run(i, r, folder=folder, loss=loss, errors=errors) -> None:
                    errors.append((r.translation_m, r.rotation_deg))
                    bar.set_description_str(f"{folder.name} {loss}")
                    bar.set_postfix_str(f"last {r.translation_m * 100:.1f} cm "
                                        f"{r.rotation_deg:.3f} deg, {r.seconds:.1f} s")
                    bar.update(1)

                res = evaluate_scene(folder, loss, protocol, params, mapping, map_file, on_run,
                                     single=args.single, label_noise=args.label_noise,
                                     noise_seed=args.noise_seed)
                results.append(res)
                if args.overlay:
                    _write_overlay(args.overlay, folder, res, params, mapping, map_file)
    finally:
        bar.close()
    print(format_table(results, paper=args.paper))
    if args.json:
        data = {"protocol": asdict(protocol), "config": args.config, "map": args.map,
                "single": args.single,
                "results": [r.to_dict() for r in results]}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(data, indent=1))
        print(f"all numbers written to {args.json}")
    return 0


def _table_from_json(paths, paper: bool) -> int:
    import json

    from semcal_tools.protocol import SceneEvaluation, format_table

    results = []
    for path in paths:
        if not path.is_file():
            raise FileNotFoundError(f"evaluation JSON not found: {path}")
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not JSON ({exc})") from None
        for item in data.get("results", []) if isinstance(data, dict) else []:
            try:
                results.append(SceneEvaluation.from_dict(item))
            except ValueError as exc:
                raise ValueError(f"{path}: {exc}") from None
    if not results:
        raise ValueError("no evaluation results in the given JSON files")
    print(format_table(results, paper=paper))
    return 0


def _write_overlay(pattern: str, folder, result, params, mapping, map_file) -> None:
    from pathlib import Path

    from semcal_ros.io.files import read_camera_info, read_rgb_image, write_rgb_image
    from semcal_ros.io.ply import read_ply
    from semcal_ros.engine.overlay import render_overlay
    from semcal_ros.engine.problem import mapping_for

    cloud = read_ply(map_file or folder / "map.ply")
    camera = read_camera_info(folder / "camera_info.yaml")
    rgb = read_rgb_image(folder / "image.png")
    out = Path(pattern.replace("{scene}", folder.name).replace("{loss}", result.loss))
    write_rgb_image(out, render_overlay(cloud, camera, result.best, rgb,
                                                mapping_for(params, mapping), params.render))
