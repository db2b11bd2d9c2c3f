"""Export a trained actor to ONNX with its map and figures beside it (``FILE.onnx`` + ``FILE.json``)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import torch

from rl.networks import OnnxActor, RecurrentNet
from rl.ppo import Trainer

DYNAMIC = {name: {0: "batch"} for name in ("obs", "h", "c", "probs", "h_out", "c_out")}


def export_actor(actor: RecurrentNet, path: str | Path, meta: dict) -> Path:
    """Write the actor's single step (obs uint8, h, c) -> (probs, h_out, c_out) and ``meta`` as JSON."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    module = OnnxActor(actor).eval()
    example = (torch.zeros(1, 84, 84, 3, dtype=torch.uint8), *actor.initial_state(1))
    torch.onnx.export(
        module,
        example,
        str(path),
        input_names=["obs", "h", "c"],
        output_names=["probs", "h_out", "c_out"],
        dynamic_axes=DYNAMIC,
        opset_version=17,
        dynamo=False,
    )
    path.with_suffix(".json").write_text(json.dumps({**meta, "hidden": actor.hidden}, indent=1) + "\n")
    return path


def export_trainer(trainer: Trainer, path: str | Path, wall_s: float, pretraining: dict | None = None) -> Path:
    """The trainer's actor, with the map it learned, its configuration and its reward curve (and the memory
    pretraining's settings and history, when there was one)."""
    return export_actor(
        trainer.actor,
        path,
        {
            "map": trainer.grid.to_json(),
            "exclude_last": trainer.cfg.exclude_last,
            "steps": trainer.global_step,
            "wall_s": round(wall_s, 1),
            "train": asdict(trainer.cfg),
            **({"pretrain": pretraining} if pretraining else {}),
            "curve": [
                {k: v for k, v in row.items() if k in ("step", "mean_return", "batch_length")} for row in trainer.curve
            ],
        },
    )
