"""Checkpoints of a PPO run (rl/ppo.py): save, resume, and a curriculum start from another run.

``init_from`` copies the parameters of another checkpoint whose shapes match (encoder, LSTM; heads only
when the number of locations is the same): a curriculum from a smaller map.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import nn

from rl.gridmap import GridMap
from rl.train_config import TrainConfig

if TYPE_CHECKING:
    from rl.ppo import Trainer

log = logging.getLogger(__name__)


def save_checkpoint(trainer: Trainer, path: Path) -> None:
    """Networks, optimiser, step count and reward curve; written to a temporary file, then renamed."""
    tmp = Path(path).with_suffix(".tmp")
    torch.save(
        {
            "config": asdict(trainer.cfg),
            "grid": trainer.grid.to_json(),
            "actor": trainer.actor.state_dict(),
            "critic": trainer.critic.state_dict(),
            "optimizer": trainer.optimizer.state_dict(),
            "global_step": trainer.global_step,
            "curve": trainer.curve,
            "history": trainer.history,
        },
        tmp,
    )
    tmp.replace(path)


def resume_trainer(make: Callable[[TrainConfig, GridMap], Trainer], path: Path, total_steps: int | None) -> Trainer:
    """A saved run continued: ``make(config, grid)`` builds the trainer, which the checkpoint then fills
    (the environments restart; networks, optimiser and counters carry on)."""
    ckpt = torch.load(path, weights_only=False)
    # runs saved before the auxiliary loss existed have no aux head: they continue without it
    cfg = TrainConfig(**{"aux_coef": 0.0, **ckpt["config"]})
    if total_steps is not None:
        cfg.total_steps = total_steps
    init_from, cfg.init_from = cfg.init_from, ""  # the saved networks replace any initialisation
    trainer = make(cfg, GridMap.from_json(ckpt["grid"]))
    trainer.cfg.init_from = init_from
    try:
        trainer.actor.load_state_dict(ckpt["actor"])
    except RuntimeError as exc:
        raise ValueError(
            f"{path}: the checkpoint's actor does not match its configuration "
            f"(aux_coef {cfg.aux_coef}): {str(exc).splitlines()[0]}"
        ) from exc
    trainer.critic.load_state_dict(ckpt["critic"])
    trainer.optimizer.load_state_dict(ckpt["optimizer"])
    trainer.global_step, trainer.curve = ckpt["global_step"], ckpt["curve"]
    trainer.history = {**trainer.history, **ckpt.get("history", {})}
    return trainer


def init_from_checkpoint(path: Path, nets: dict[str, nn.Module]) -> None:
    """Curriculum: copy the parameters of a checkpoint whose shapes match into ``nets`` (by checkpoint key,
    "actor" and "critic"); the rest keep their initialisation."""
    ckpt = torch.load(path, weights_only=False)
    copied = []
    for name, net in nets.items():
        own = net.state_dict()
        same = {k: v for k, v in ckpt[name].items() if k in own and own[k].shape == v.shape}
        own.update(same)
        net.load_state_dict(own)
        copied += [f"{name}.{k}" for k in same]
    if not copied:
        raise ValueError(f"{path}: no parameter of matching shape to initialise from")
    log.info("initialised %d tensors from %s", len(copied), path)
