"""The self-contained ``controller.pt``: :func:`save_controller` writes a controller (weights, kind, ``init_kwargs``,
the ``ControlConfig`` and the ``SimConfig``) through ``freeform.checkpoint``; :func:`read_controller` rebuilds it, for
any box where the kind allows, from that file, a results folder holding one, or a control run's directory."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn

from freeform.agents.networks import rebuild
from freeform.agents.networks.controller_heads import wave_follows_heading
from freeform.agents.networks.controllers import (
    CONTROLLERS,
    PrivilegedCritic,
    controller_observe,
    controller_step,
)
from freeform.agents.networks.gated import PLAYABLE, playable_kind
from freeform.body import bounding_box
from freeform.checkpoint import load_checkpoint, save_checkpoint
from freeform.envs.control import ControlConfig
from freeform.sim import SimConfig

CONTROLLER_FILE = "controller.pt"


@dataclass
class SavedController:
    """A controller read back by :func:`read_controller`: the network (weights loaded, built for the box asked
    for), its kind, the episode's ``ControlConfig`` it was trained under, its ``SimConfig`` (None where the file
    has none) and the file it came from."""

    controller: nn.Module
    kind: str
    control: Any
    sim: Any
    path: Path

    def policy_for(self, bodies: Any) -> MeanPolicy:
        """This controller built for a box that holds ``bodies`` (:func:`controller_for`), acting by its mean
        command: what a task that scores designs under it drives them with (``freeform.envs.tasks.
        FrozenController``)."""
        return MeanPolicy(controller_for(self.path, bodies).controller.eval())


@dataclass
class MeanPolicy:
    """A controller acting by its mean command, deterministically: ``policy(obs [N, C, Bx, By, Bz], state) ->
    (actions [N, Bx·By·Bz], state)`` (``state`` None at an episode's start; a feed-forward controller keeps None)."""

    net: nn.Module

    @property
    def box(self) -> tuple[int, int, int]:
        return tuple(int(b) for b in self.net.box)  # type: ignore[return-value]

    @torch.no_grad()
    def __call__(self, obs: torch.Tensor, state: tuple[torch.Tensor, ...] | None
                 ) -> tuple[torch.Tensor, tuple[torch.Tensor, ...] | None]:
        outputs, state = controller_step(self.net, obs, state)
        return self.net.distribution.mode(outputs[:3]), state

    def observe(self, state: tuple[torch.Tensor, ...] | None, reward: torch.Tensor) -> tuple[torch.Tensor, ...] | None:
        """``state`` after a step that earned ``reward`` ``[N]`` (a controller that reads rewards is told)."""
        return controller_observe(self.net, state, reward)


def save_controller(path: str | Path, controller: nn.Module, control: Any, sim: Any = None) -> Path:
    """Write ``controller.pt``, self-contained: ``{"controller": {"kind", "init_kwargs", "weights"}, "control":
    the ControlConfig's fields, "sim": the SimConfig as a dict or None}``, atomically through
    ``freeform.checkpoint.save_checkpoint`` (read with ``weights_only``). ``control`` may be a ``ControlRunConfig``
    (its episode's fields are kept). Returns the path written."""
    episode = {f.name: getattr(control, f.name) for f in dataclasses.fields(ControlConfig)}
    episode["privileged_critic"] = False  # (the file holds the actor: it acts on what the sensors give)
    if isinstance(controller, PrivilegedCritic):
        controller = controller.controller
    _check_wave_frame(controller.init_kwargs.get("wave"), ControlConfig(**episode))
    return save_checkpoint(path, {
        "controller": {"kind": playable_kind(controller), "init_kwargs": dict(controller.init_kwargs),
                       "weights": {k: v.detach().cpu() for k, v in controller.state_dict().items()}},
        "control": episode, "sim": dataclasses.asdict(sim) if sim is not None else None})


def _check_wave_frame(wave: dict[str, Any] | None, control: ControlConfig) -> None:
    """A wave head saved with a ``ControlConfig`` whose heading it cannot follow is refused: one that turns with
    the heading channels in the heading's frame (they are 0 there), or one that does not turn where the world's
    frame asks it to (random headings; ``controller_heads.wave_follows_heading``). Files without heading channels
    from before steering stay valid where the heading does not vary."""
    if not wave:
        return
    turns = wave.get("heading_channels") is not None
    if turns and control.frame == "heading":
        raise ValueError("this controller's wave turns with the heading channels, which the heading's frame zeroes "
                         "(control.frame=heading): build it for an env in that frame (its wave then runs along x)")
    if not turns and control.headings == "random" and wave_follows_heading(control):
        raise ValueError("this controller's wave runs along x whatever the heading (built for the heading's frame or "
                         "for no heading), and control.headings=random in the world's frame asks it to turn: save it "
                         "with the frame and headings it was built for")


def read_controller(source: str | Path, box: tuple[int, int, int] | None = None) -> SavedController:
    """The controller in ``source``, rebuilt: a ``controller.pt`` (:func:`save_controller`; also the older files of
    ``lab/control.py``, a PPO checkpoint beside its ``args.json``), a folder holding one, or a control or
    co-design run's directory (its ``checkpoints/last.pt``; a co-design run's controller part). ``box``: build it for
    this box instead of the one it trained in — any box for the kinds that fit any box, refused with the reason for
    the MLP."""
    path = Path(source)
    if path.is_dir():
        candidates = (path / CONTROLLER_FILE, path / "checkpoints" / "last.pt")
        found = next((c for c in candidates if c.is_file()), None)
        if found is None:
            raise ValueError(f"{source}: holds neither {CONTROLLER_FILE} nor checkpoints/last.pt (a control run's)")
        path = found
    payload = load_checkpoint(path)
    kind, kwargs, weights, control, sim = _saved_parts(payload, path)
    if kind not in PLAYABLE:
        raise ValueError(f"{path}: holds a controller of kind {kind!r}, none of {list(PLAYABLE)} (a newer freeform's?)")
    controller = rebuild(PLAYABLE[kind], kwargs)
    saved_box = tuple(int(b) for b in kwargs["box"])
    if box is not None and tuple(int(b) for b in box) != saved_box:
        if not controller.fits_any_box:  # (the instance's: a gate fits any box where its experts all do)
            raise ValueError(f"{path}: its {kind!r} controller learnt each cell of its box {saved_box} apart and runs "
                             f"on that box only, and these bodies need the box {tuple(box)}")
        controller = rebuild(PLAYABLE[kind], {**kwargs, "box": tuple(int(b) for b in box)})
    controller.load_state_dict(weights)
    return SavedController(controller, kind, control, sim, path)


def body_box(grids: Any) -> tuple[int, int, int]:
    """The box that holds every body of ``grids`` (uint8 ``[M, X, Y, Z]``) cropped to its bounding box: the
    ``ControlEnv``'s ``box`` for them."""
    lo, hi = bounding_box(grids)
    return tuple(int(b) for b in (hi - lo).amax(0))  # type: ignore[return-value]


def controller_for(source: str | Path, grids: Any) -> SavedController:
    """The controller in ``source`` (:func:`read_controller`) built for a box that holds the bodies of ``grids``:
    the box it trained in where they fit it (its weights see what they saw in training), else theirs (refused for a
    kind that fits one box, with the reason)."""
    saved = read_controller(source)
    need, trained = body_box(grids), tuple(int(b) for b in saved.controller.box)
    if all(b <= t for b, t in zip(need, trained, strict=True)):
        return saved
    return read_controller(saved.path, box=need)


def _saved_parts(payload: dict[str, Any], path: Path) -> tuple[str, dict[str, Any], dict[str, Any], Any, Any]:
    """(kind, init_kwargs, weights, ControlConfig, SimConfig or None) from any of the files
    :func:`read_controller` reads."""
    if "controller" in payload:  # save_controller's
        part = payload["controller"]
        sim = _structured(SimConfig, payload["sim"]) if payload.get("sim") is not None else None
        return part["kind"], dict(part["init_kwargs"]), part["weights"], ControlConfig(**payload["control"]), sim
    if "policy_class" not in payload:
        raise ValueError(f"{path}: neither a controller.pt nor a PPO or run checkpoint")
    name = payload["policy_class"].rsplit(":", 1)[-1]
    kwargs, weights = dict(payload["policy_kwargs"]), payload["ppo"]["policy"]
    if name == "PrivilegedCritic":  # its controller part: the actor (and its own critic)
        kind, kwargs = kwargs["kind"], dict(kwargs["controller"])
        weights = {k[len("controller."):]: v for k, v in weights.items() if k.startswith("controller.")}
    elif name == "CodesignActorCritic":  # a co-design run: its controller part
        start, stop = kwargs["control_channels"]
        weights = {k[len("controller."):]: v for k, v in weights.items() if k.startswith("controller.")}
        if "controller_kwargs" in kwargs:  # (a kind or head of its own)
            kind, kwargs = kwargs["controller"], dict(kwargs["controller_kwargs"])
        else:
            kind = "conv"
            kwargs = dict(channels=stop - start, box=(kwargs["resolution"],) * 3, mask_channel=kwargs["mask_channel"],
                          filled_channel=kwargs["filled_channel"], hidden=kwargs["controller_hidden"],
                          log_std=kwargs["log_std"])
    else:
        kind = next((k for k, cls in CONTROLLERS.items() if cls.__name__ == name), None)
        if kind is None:
            raise ValueError(f"{path}: its policy {name} is no controller (one of {list(CONTROLLERS)})")
    if "config" in payload:  # a run's checkpoint: its control and sim sections
        run = payload["config"]
        if run.get("control") is None:
            raise ValueError(f"{path}: a run without a control section (a design run) has no controller")
        episode = {k: v for k, v in run["control"].items() if k in {f.name for f in dataclasses.fields(ControlConfig)}}
        control = _structured(ControlConfig, {**episode, "privileged_critic": False})
        control.validate()
        return kind, kwargs, weights, control, _structured(SimConfig, run.get("sim") or {})
    args = path.parent / "args.json"  # lab/control.py's older controller.pt: a PPO checkpoint
    if not args.is_file():
        raise ValueError(f"{path}: a PPO checkpoint without its ControlConfig (no run config, no args.json beside it)")
    saved = json.loads(args.read_text())
    control = ControlConfig(burn_in=saved["burn_in"], command_rate=saved.get("command_rate"),
                            ramp=saved.get("ramp", False))
    return kind, kwargs, weights, control, SimConfig()


def _structured(schema: type, data: dict[str, Any]) -> Any:
    """``data`` (a section of a saved config) as the dataclass ``schema``: its defaults where ``data`` has none, the
    types checked (OmegaConf's structured merge)."""
    from omegaconf import OmegaConf

    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(schema), data))


__all__ = ["CONTROLLER_FILE", "MeanPolicy", "SavedController", "body_box", "controller_for", "read_controller", "save_controller"]
