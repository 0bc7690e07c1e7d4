"""``freeform-render``: pictures, gait videos and exports of the bodies a training run designed.

Examples (RUN is a run directory, or one ``records/epoch_<e>.npz`` file)::

    freeform-render RUN                              # PNG of the last epoch's best body
    freeform-render RUN --epoch 40 --bodies best,median,random,17
    freeform-render RUN --grid 16                    # a sheet of the 16 best bodies, like the paper's figures
    freeform-render RUN --video --seconds 5          # GIF of the best robot's simulated gait (--video-format mp4)
    freeform-render RUN --history --export vxd,obj,stl,vox   # voxcraft-viz replay + files for other tools
    freeform-render --random 16 --grid 16            # no run: designs of an untrained (N(0, I)) policy
    freeform-render RUN_A RUN_B ... --grid 4 --out D # several runs: D/sheet.png, a row of each run's 4 best

Files go to ``RUN/renders/epoch_<e>/`` (or ``--out``); their paths are printed, one per line.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from freeform.render import (
    RenderConfig,
    VideoConfig,
    contact_sheet,
    gait_simulator,
    render_grid,
    render_grids,
    render_recording,
    simulate_gait,
    write_png,
    write_video,
)

PICKS = ("best", "median", "worst", "random")
EXPORTS = ("vxd", "obj", "stl", "vox")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="freeform-render",
        description="Render the bodies of a freeform training run: PNGs, a sheet (--grid), a gait video (--video), "
        "voxcraft/mesh/MagicaVoxel exports.",
        epilog=__doc__.split("Examples", 1)[1].split("Files go", 1)[0].split("::", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run", nargs="*", help="run directory, or a records/epoch_<e>.npz file (several: with --grid "
                   "and --out only, a sheet with a row of best bodies per run)")
    p.add_argument("--epoch", type=int, default=None, help="epoch whose record to read (default: the last)")
    p.add_argument("--bodies", default="best",
                   help=f"comma-separated picks: {', '.join(PICKS)} or episode indices (default: best)")
    p.add_argument("--out", type=Path, default=None, help="output directory (default: RUN/renders/epoch_<e>)")
    p.add_argument("--size", type=int, default=384, help="image edge in pixels (default: 384)")
    p.add_argument("--frame", choices=("grid", "body"), default="grid",
                   help="frame the whole design space (grid, one scale for all) or zoom to the voxels (body)")
    p.add_argument("--azimuth", type=float, default=RenderConfig.azimuth,
                   help="camera azimuth in degrees about +z from +x (default: -60, the paper's view; -120 looks "
                        "up a slope or staircase rising towards +x)")
    p.add_argument("--elevation", type=float, default=RenderConfig.elevation,
                   help="camera elevation in degrees (default: 30)")
    p.add_argument("--no-removed", action="store_true", help="hide the translucent voxels outside the body")
    p.add_argument("--grid", type=int, default=0, metavar="N", help="also write sheet.png of N bodies")
    p.add_argument("--grid-order", choices=("best", "random", "first"), default="best",
                   help="which N bodies the sheet shows (default: the N best)")
    p.add_argument("--columns", type=int, default=None, help="sheet columns (default: about sqrt(N))")
    p.add_argument("--video", action="store_true", help="simulate the first picked body and write its gait video")
    p.add_argument("--video-format", choices=("gif", "mp4"), default="gif",
                   help="gif (built in) or mp4 (needs pip install 'freeform[video]')")
    p.add_argument("--seconds", type=float, default=VideoConfig.seconds, help="simulated seconds of the video")
    p.add_argument("--fps", type=float, default=VideoConfig.fps, help="frames per simulated second")
    p.add_argument("--history", action="store_true", help="write the simulation as a voxcraft-viz .history")
    p.add_argument("--export", default="", help=f"comma-separated formats per picked body: {', '.join(EXPORTS)}"
                   " (vxd also writes the run's base.vxa)")
    p.add_argument("--random", type=int, default=0, metavar="N",
                   help="instead of a run: N designs of a policy sampling a ~ N(0, I) (DesignEnv)")
    p.add_argument("--materials", type=int, default=4, help="k for --random (2 volume, 4 locomotion)")
    p.add_argument("--resolution", type=int, default=20, help="ρ for --random")
    p.add_argument("--seed", type=int, default=0, help="seed of --random and of the 'random' pick")
    p.add_argument("--arch", choices=("auto", "cpu", "cuda"), default="auto", help="simulator device for --video")
    return p


# ------------------------------------------------------------------------------------------------ inputs


def read_designs(source: str | Path, epoch: int | None = None) -> tuple[np.ndarray, np.ndarray, int, Path]:
    """``(final_grids [E, ρ, ρ, ρ] uint8, rewards [E], epoch, run_dir)`` of a run directory's record of ``epoch``
    (default: the last) or of one record file; each body turned to the placement it was scored at
    (``EpochRecord.placed_grids``)."""
    from freeform.records import list_records, read_record, record_path

    source = Path(source)
    if source.is_file():
        record = read_record(source)
        run_dir = source.parent.parent if source.parent.name == "records" else source.parent
    elif source.is_dir():
        if epoch is None:
            paths = list_records(source)
            if not paths:
                raise ValueError(f"run directory {source} holds no design records (records/epoch_*.npz)")
            record = read_record(paths[-1])
        else:
            path = record_path(source, epoch)
            if not path.is_file():
                have = [int(p.stem.split("_")[1]) for p in list_records(source)]
                raise ValueError(f"epoch must be one of the recorded epochs {have[:5]}…{have[-3:]}, got {epoch}"
                                 if len(have) > 8 else f"epoch must be one of the recorded epochs {have}, got {epoch}")
            record = read_record(path)
        run_dir = source
    else:
        raise ValueError(f"run must be a run directory or a record file, got {str(source)!r} (not found)")
    return record.placed_grids(), record.rewards.astype(np.float64), record.epoch, run_dir


def run_sim_config(run_dir: Path) -> Any:
    """The run's ``SimConfig``: from ``.hydra/config.yaml``, else ``checkpoints/last.pt``, else the defaults."""
    from freeform.sim import SimConfig

    hydra_cfg = run_dir / ".hydra" / "config.yaml"
    try:
        if hydra_cfg.is_file():
            from omegaconf import OmegaConf

            from freeform.config import to_dataclass

            return to_dataclass(OmegaConf.load(hydra_cfg)).sim
        last = run_dir / "checkpoints" / "last.pt"
        if last.is_file():
            from freeform.checkpoint import load_checkpoint
            from freeform.config import from_container

            return from_container(load_checkpoint(last)["config"]).sim
    except (ValueError, KeyError, OSError) as exc:
        print(f"freeform-render: could not read the run's config ({exc}); using the default simulation settings",
              file=sys.stderr)
    return SimConfig()


def random_designs(n: int, materials: int, resolution: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` final grids of DesignEnv driven by actions a ~ N(0, I) (an untrained policy), and their volumes as
    rewards (the volume task's reward: the body's voxel count)."""
    from freeform.body import largest_component
    from freeform.envs.design import DesignEnv, EnvConfig
    from freeform.evolve import untrained_design_grids

    grids = untrained_design_grids(DesignEnv(n, EnvConfig(resolution=resolution),
                                             materials=materials, compute_metrics=False), seed)
    volumes = (largest_component(grids) > 0).flatten(1).sum(dim=1)
    return grids.numpy(), volumes.numpy().astype(np.float64)


def pick(spec: str, rewards: np.ndarray, seed: int) -> list[tuple[str, int]]:
    """``[(label, index)]`` for a ``--bodies`` spec such as ``best,median,3``."""
    order = np.argsort(rewards, kind="stable")
    rng = np.random.default_rng(seed)
    out = []
    for token in (t.strip() for t in spec.split(",") if t.strip()):
        if token == "best":
            out.append(("best", int(order[-1])))
        elif token == "worst":
            out.append(("worst", int(order[0])))
        elif token == "median":
            out.append(("median", int(order[(len(order) - 1) // 2])))
        elif token == "random":
            out.append(("random", int(rng.integers(len(rewards)))))
        elif token.isdigit() and int(token) < len(rewards):
            out.append(("episode", int(token)))
        else:
            raise ValueError(f"--bodies entries must be one of {PICKS} or an episode index 0..{len(rewards) - 1}, "
                             f"got {token!r}")
    if not out:
        raise ValueError("--bodies must name at least one body")
    return out


# ------------------------------------------------------------------------------------------------ main


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return _run(args)
    except ValueError as exc:
        print(f"freeform-render: error: {exc}", file=sys.stderr)
        return 2


@dataclass
class _Designs:
    """The designs one invocation shows: ``grids`` and their ``bodies`` (largest components) ``[E, ρ, ρ, ρ]``
    uint8, what is drawn of them (``shown``), ``rewards [E]``, the record's ``epoch`` (None: ``--random``), where
    the files go (``out``) and the run's ``SimConfig`` (None: the defaults)."""

    grids: np.ndarray
    bodies: np.ndarray
    shown: np.ndarray
    rewards: np.ndarray
    epoch: int | None
    out: Path
    sim_config: Any


def _run(args: argparse.Namespace) -> int:
    if args.size < 16:
        raise ValueError(f"--size must be >= 16 pixels, got {args.size}")
    if len(args.run) > 1:
        return _runs_sheet(args)
    args.run = args.run[0] if args.run else None
    exports = [e.strip() for e in args.export.split(",") if e.strip()]
    unknown = sorted(set(exports) - set(EXPORTS))
    if unknown:
        raise ValueError(f"--export formats must be among {EXPORTS}, got {unknown}")
    designs = _designs(args)
    cfg = RenderConfig(size=args.size, frame=args.frame, azimuth=args.azimuth, elevation=args.elevation)
    picks = pick(args.bodies, designs.rewards, args.seed)
    written = _pictures(args, designs, cfg, picks)
    written += _exports(exports, designs, picks)
    if args.video or args.history:
        written += _gait(args, designs, cfg, picks[0])
    for path in written:
        print(path)
    return 0


def _designs(args: argparse.Namespace) -> _Designs:
    """The run's (or ``--random``'s) designs, their bodies and where their files go."""
    from freeform.body import largest_component

    if args.random:
        if args.run:
            raise ValueError("give either a run or --random N, not both")
        grids, rewards = random_designs(args.random, args.materials, args.resolution, args.seed)
        epoch, sim_config = None, None
        out = args.out if args.out is not None else Path("renders") / "random"
    elif args.run:
        grids, rewards, epoch, run_dir = read_designs(args.run, args.epoch)
        out = args.out if args.out is not None else run_dir / "renders" / f"epoch_{epoch:06d}"
        sim_config = run_sim_config(run_dir)
    else:
        raise ValueError("give a run directory (or record file), or --random N")
    if len(grids) == 0:
        raise ValueError("the record holds no designs")
    bodies = largest_component(torch.from_numpy(np.ascontiguousarray(grids))).numpy()
    shown = grids if not args.no_removed else bodies
    return _Designs(grids, bodies, shown, rewards, epoch, out, sim_config)


def _pictures(args: argparse.Namespace, d: _Designs, cfg: RenderConfig, picks: list[tuple[str, int]]) -> list[Path]:
    """A PNG of each picked body, and the sheet of ``--grid`` bodies."""
    where = f"epoch {d.epoch}" if d.epoch is not None else "random policy"
    score = "reward" if d.epoch is not None else "volume"  # --random designs are scored by their body volume
    written = []
    for label, i in picks:
        volume = int((d.bodies[i] > 0).sum())
        caption = [f"{where}, {label} #{i}", f"{score} {d.rewards[i]:.4g}", f"{volume} voxels"]
        written.append(write_png(d.out / f"{label}_{i}.png", render_grid(d.shown[i], d.bodies[i], cfg, caption)))
    if args.grid:
        n = min(args.grid, len(d.grids))
        if args.grid_order == "best":
            idx = np.argsort(-d.rewards, kind="stable")[:n]
        elif args.grid_order == "random":
            idx = np.sort(np.random.default_rng(args.seed).choice(len(d.grids), n, replace=False))
        else:
            idx = np.arange(n)
        small = replace(cfg, size=max(96, min(args.size, 256)), caption_size=11)
        captions = [[f"#{i}  {score} {d.rewards[i]:.3g}"] for i in idx]
        images = render_grids(d.shown[idx], d.bodies[idx], small, captions)
        written.append(write_png(d.out / "sheet.png", contact_sheet(images, args.columns)))
    return written


def _exports(exports: list[str], d: _Designs, picks: list[tuple[str, int]]) -> list[Path]:
    """Each picked body in each of the ``--export`` formats (a VXD with the run's base VXA)."""
    written: list[Path] = []
    first = picks[0][1]
    for fmt in exports:
        from freeform.io import export_body, write_vxa

        if not (d.bodies[first] > 0).any():
            raise ValueError(f"body #{first} is empty: nothing to export")
        for label, i in picks:
            written.append(export_body(d.out / f"{label}_{i}.{fmt}", d.bodies[i], d.sim_config))
        if fmt == "vxd":
            written.append(write_vxa(d.out / "base.vxa", d.sim_config))
    return written


def _gait(args: argparse.Namespace, d: _Designs, cfg: RenderConfig, first_pick: tuple[str, int]) -> list[Path]:
    """The first picked body's simulated gait: its video (``--video``) and voxcraft-viz history (``--history``)."""
    from freeform.sim import SimConfig

    first_label, first = first_pick
    if not (d.bodies[first] > 0).any():
        raise ValueError(f"body #{first} is empty: nothing to simulate")
    base = d.sim_config if d.sim_config is not None else SimConfig()
    simulator = gait_simulator(base, args.seconds, args.arch)
    recording = simulate_gait(simulator, d.bodies[first], args.fps)
    written = []
    if args.video:
        frames = render_recording(recording, 0, replace(cfg, frame="grid"))
        written.append(write_video(d.out / f"{first_label}_{first}_gait.{args.video_format}", frames, args.fps))
    if args.history:
        from freeform.io import write_history

        written.append(write_history(d.out / f"{first_label}_{first}.history", recording))
    return written


def _runs_sheet(args: argparse.Namespace) -> int:
    """Several runs side by side (e.g. one per task): ``--out/sheet.png``, row r = the ``--grid`` best bodies of run
    r's record (``--epoch``, default each run's last), captioned with the run's experiment and the reward."""
    from freeform.body import largest_component

    if not args.grid or args.out is None:
        raise ValueError("several runs make one sheet: give --grid N (bodies per run) and --out DIR")
    if args.video or args.history or args.export or args.random:
        raise ValueError("several runs make one sheet only: --video, --history, --export and --random take one run")
    cfg = RenderConfig(size=max(96, min(args.size, 256)), frame=args.frame, azimuth=args.azimuth,
                       elevation=args.elevation, caption_size=11)
    images = []
    for run in args.run:
        grids, rewards, epoch, run_dir = read_designs(run, args.epoch)
        info = run_dir / "run_info.json"
        name = (json.loads(info.read_text()).get("experiment") if info.is_file() else None) or run_dir.name
        best = np.argsort(-rewards, kind="stable")[: args.grid]
        if len(best) < args.grid:
            raise ValueError(f"run {run} recorded {len(best)} designs in epoch {epoch}, fewer than --grid {args.grid}")
        bodies = largest_component(torch.from_numpy(np.ascontiguousarray(grids[best]))).numpy()
        shown = grids[best] if not args.no_removed else bodies
        images.extend(render_grids(shown, bodies, cfg, [[name, f"reward {rewards[i]:.3g}"] for i in best]))
    print(write_png(args.out / "sheet.png", contact_sheet(images, args.grid)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
