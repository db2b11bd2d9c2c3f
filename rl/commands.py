"""``objslam train-lc`` and ``objslam eval-lc``: RL loop-closure training and evaluation (SPEC 2, 6.9)."""

from __future__ import annotations

import json
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

POLICY_DIR = Path(__file__).resolve().parents[1] / "models" / "lc"
INIT_CHECKPOINT = "config1.init.pt"  # networks of the config1 policy before memory pretraining: default --init-from
TABLE_3_1 = {
    "config1": (77.8, 63.5),
    "config2": (78.2, 71.2),
    "config3": (82.5, 63.1),
    "config4": (85.6, 68.7),
    "config5": (76.4, 64.4),
    "config6": (83.1, 70.6),
}


class BatchMode(StrEnum):
    entropy = "entropy"
    fixed = "fixed"


def register(app: typer.Typer, console, user_error: type[Exception]) -> None:
    """Add the two commands to the ``objslam`` application."""

    @app.command("train-lc")
    def train_lc(
        out: Annotated[Path, typer.Option("--out", help="policy file FILE.onnx (FILE.json, .pt, .png beside it)")],
        grid: Annotated[
            str, typer.Option("--map", help="shipped configuration (config1..config6) or map file")
        ] = "config1",
        from_map: Annotated[
            Path | None,
            typer.Option("--from-map", help="a run output or state directory: train for its grid world (grid.json)"),
        ] = None,
        cell_m: Annotated[
            float | None,
            typer.Option(
                "--cell", help="--from-map: rebuild the grid with this cell size in metres (default: its grid.json)"
            ),
        ] = None,
        steps: Annotated[int, typer.Option("--steps", help="environment steps over all actors")] = 300_000,
        batch: Annotated[
            BatchMode, typer.Option("--batch", help="entropy-based (eq. 3.20) or fixed")
        ] = BatchMode.entropy,
        n_steps: Annotated[int, typer.Option("--n-steps", help="fixed batch: steps per actor")] = 128,
        b1: Annotated[int, typer.Option("--b1", help="entropy batch: shortest trajectory per actor")] = 64,
        b2: Annotated[int, typer.Option("--b2", help="entropy batch: longest trajectory per actor")] = 256,
        envs: Annotated[int, typer.Option("--envs", help="parallel actors")] = 8,
        episode_steps: Annotated[int, typer.Option("--episode-steps", help="training episodes truncated here")] = 512,
        seed: Annotated[int, typer.Option("--seed")] = 0,
        threads: Annotated[int, typer.Option("--threads", help="torch threads")] = 1,
        resume: Annotated[bool, typer.Option("--resume", help="continue from FILE.pt")] = False,
        aux_targets: Annotated[
            str,
            typer.Option(
                "--aux-targets",
                help="auxiliary targets of the actor: visited, visited+here+due or visited+place+action (docs/rl.md)",
            ),
        ] = "visited",
        init_from: Annotated[
            Path | None,
            typer.Option("--init-from", help="checkpoint (.pt) whose parameters of matching shape start the networks"),
        ] = None,
        balance_first_visits: Annotated[
            bool,
            typer.Option(
                "--balance-first-visits/--no-balance-first-visits",
                help="balanced policy loss over three kinds of step: due, first visit, other (docs/rl.md)",
            ),
        ] = False,
        pretrain_epochs: Annotated[
            int,
            typer.Option(
                "--pretrain-epochs",
                help="first train the actor's visit memory on random walks, supervised, for this "
                "many epochs (0 = off; docs/rl.md)",
            ),
        ] = 0,
        pretrain_walks: Annotated[int, typer.Option("--pretrain-walks", help="random walks for pretraining")] = 512,
        pretrain_length: Annotated[int, typer.Option("--pretrain-length", help="steps per pretraining walk")] = 128,
        pretrain_policy: Annotated[
            bool,
            typer.Option(
                "--pretrain-policy/--no-pretrain-policy",
                help="after pretraining, start the policy head as a copy of the aux correct-action classifier "
                "(an imitation start that PPO fine-tunes; docs/rl.md)",
            ),
        ] = False,
    ) -> None:
        """Train a PPO loop-closure policy for a grid map and export it to ONNX."""
        try:
            from rl.export import export_trainer
            from rl.ppo import Trainer
            from rl.pretrain import PretrainConfig
            from rl.train_config import TrainConfig
        except ImportError as exc:
            raise user_error(f"training needs the train extra (pip install -e '.[train]'): {exc}") from exc
        from tqdm import tqdm

        from rl.gridmap import GridMap, MapError
        from rl.plot import plot_reward_curves

        if out.suffix != ".onnx":
            raise user_error("--out must name a .onnx file")
        if steps <= 0 or envs <= 0 or not (0 < b1 <= b2) or n_steps <= 0:
            raise user_error("--steps, --envs, --n-steps must be positive and 0 < --b1 <= --b2")
        if pretrain_epochs < 0 or (pretrain_epochs and (pretrain_walks <= 0 or pretrain_length <= 0)):
            raise user_error("--pretrain-epochs must be >= 0, --pretrain-walks and --pretrain-length positive")
        if pretrain_policy and not pretrain_epochs:
            raise user_error("--pretrain-policy needs --pretrain-epochs > 0")
        if pretrain_epochs and resume:
            raise user_error("--pretrain-epochs starts a run; it cannot be combined with --resume")
        out.parent.mkdir(parents=True, exist_ok=True)
        checkpoint = out.with_suffix(".pt")
        try:
            if resume:
                if not checkpoint.is_file():
                    raise user_error(f"no checkpoint to resume: {checkpoint}")
                trainer = Trainer.resume(checkpoint, total_steps=steps)
            else:
                grid_map = _map_of_dir(from_map, cell_m) if from_map is not None else GridMap.load(grid)
                cfg = TrainConfig(
                    map=grid_map.name,
                    total_steps=steps,
                    n_envs=envs,
                    batch=batch.value,
                    n_steps=n_steps,
                    b1=b1,
                    b2=b2,
                    seed=seed,
                    threads=threads,
                    max_episode_steps=episode_steps,
                    minibatches=min(4, envs) if envs % min(4, envs) == 0 else 1,
                    aux_targets=aux_targets,
                    init_from=str(init_from) if init_from else "",
                    balance_first_visits=balance_first_visits,
                )
                trainer = Trainer(cfg, grid_map)
        except (MapError, ValueError) as exc:
            raise user_error(str(exc)) from exc
        pretraining = _pretrain(
            trainer,
            PretrainConfig(
                epochs=pretrain_epochs,
                walks=pretrain_walks,
                length=pretrain_length,
                seed=seed,
                policy_from_aux=pretrain_policy,
            ),
            console,
            user_error,
        )
        bar = tqdm(total=steps, initial=trainer.global_step, unit="step", desc=f"train-lc {trainer.grid.name}")

        def progress(step: int, stats: dict) -> None:
            bar.update(step - bar.n)
            taken, due = max(stats["lc_taken"], 1), max(stats["lc_due"], 1)
            ret = stats["mean_return"]
            bar.set_postfix(
                ret="-" if ret is None else f"{ret:.0f}",
                P=f"{stats['lc_correct'] / taken:.2f}",
                R=f"{stats['lc_correct'] / due:.2f}",
                n=stats["batch_length"],
            )

        if pretraining:
            trainer.history = {"pretrain": pretraining, "wall_s": pretraining["history"][-1]["wall_s"]}
        result = trainer.train(checkpoint, progress)
        bar.close()
        trainer.history["wall_s"] += result.wall_s  # all segments: pretraining, PPO, resumed PPO
        trainer.save(checkpoint)
        export_trainer(trainer, out, trainer.history["wall_s"], trainer.history["pretrain"])
        plot_reward_curves(
            {f"{trainer.grid.name} ({trainer.cfg.batch})": trainer.curve},
            out.with_suffix(".png"),
            f"loop-closure PPO on {trainer.grid.name}",
        )
        console.print(
            f"{trainer.global_step} steps in {trainer.history['wall_s']:.0f} s -> {out} "
            f"(+ {out.with_suffix('.json').name}, {checkpoint.name}, {out.with_suffix('.png').name})"
        )

    @app.command("eval-lc")
    def eval_lc(
        policies: Annotated[list[Path] | None, typer.Argument(help="policy files (default: the shipped ones)")] = None,
        runs: Annotated[int, typer.Option("--runs", help="runs per configuration")] = 20,
        max_steps: Annotated[int, typer.Option("--max-steps", help="steps per run at most")] = 20_000,
        seed: Annotated[int, typer.Option("--seed")] = 10_000,
        baselines: Annotated[
            bool, typer.Option("--baselines/--no-baselines", help="also random, no-loop-closure and oracle")
        ] = True,
        as_json: Annotated[bool, typer.Option("--json", help="print JSON")] = False,
        write: Annotated[Path | None, typer.Option("--write", help="record the table in this benchmarks file")] = None,
    ) -> None:
        """Table-3.1-style precision and recall of loop-closure policies in their grid worlds."""
        from rl.evaluate import evaluate
        from rl.policy import NoLoopPolicy, OnnxPolicy, OraclePolicy, RandomPolicy

        files = policies or sorted(POLICY_DIR.glob("config*.onnx"))
        if not files:
            raise user_error(f"no policy files given and none in {POLICY_DIR}")
        results: dict[str, dict] = {}
        rows = []
        for path in files:
            if not path.is_file() or not path.with_suffix(".json").is_file():
                raise user_error(f"{path}: a policy needs FILE.onnx and FILE.json")
            policy = OnnxPolicy(path)
            exclude = int(policy.meta.get("exclude_last", 4))
            res = evaluate(policy.grid, policy, runs, seed, max_steps, exclude)
            results[policy.grid.name] = res.to_json()
            base = {}
            if baselines:
                for b in (RandomPolicy(seed), NoLoopPolicy(), OraclePolicy()):
                    base[b.name] = evaluate(policy.grid, b, runs, seed, max_steps, exclude)
                results[policy.grid.name]["baselines"] = {k: v.to_json() for k, v in base.items()}
            rows.append(_row(policy, res, base))
        if as_json:
            typer.echo(json.dumps(results, indent=1))
        header = [
            "config",
            "grid",
            "locations",
            "dissertation P/R %",
            "policy P/R %",
            "due",
            "taken",
            "runs complete",
            "random P/R %",
            "no-LC P/R %",
            "oracle P/R %",
            "train steps",
            "train wall s",
        ]
        if not as_json:
            from bench.report import show_table

            show_table(console, "RL loop closure (Table 3.1 protocol)", header, rows)
        if write is not None:
            from bench.report import markdown_table, record

            mean_p = sum(r["precision"] for r in results.values()) / len(results)
            mean_r = sum(r["recall"] for r in results.values()) / len(results)
            record(
                "eval-lc",
                "RL loop closure in the grid worlds (issue 5)",
                f"objslam eval-lc --runs {runs} --max-steps {max_steps} --write {write}",
                markdown_table(header, rows),
                f"Mean over configurations: precision {100 * mean_p:.1f} %, recall {100 * mean_r:.1f} % "
                f"(target >= 95 % / >= 80 %; dissertation 80 % / 67 %).",
                path=write,
            )


def _pretrain(trainer, cfg, console, user_error) -> dict | None:
    """Supervised pretraining of the visit memory (rl/pretrain.py) before PPO; its settings and history."""
    if not cfg.epochs:
        return None
    from dataclasses import asdict

    from tqdm import tqdm

    from rl.pretrain import MemoryPretrainer

    epochs = cfg.epochs
    try:
        pretrainer = MemoryPretrainer(trainer, cfg)
    except ValueError as exc:
        raise user_error(str(exc)) from exc
    bar = tqdm(total=epochs, unit="epoch", desc=f"pretrain memory {trainer.grid.name}")

    def progress(epoch: int, row: dict) -> None:
        bar.update(epoch - bar.n)
        bar.set_postfix(
            loss=f"{row['loss']:.3f}",
            due=f"{row['due_recalled']:.2f}",
            first=f"{row['first_visits_recognised']:.2f}",
            P=f"{row['action_precision']:.2f}",
            R=f"{row['action_recall']:.2f}",
        )

    history = pretrainer.run(progress)
    bar.close()
    last = history[-1]
    console.print(
        f"visit memory after {epochs} epochs ({last['wall_s']:.0f} s), held-out walks: due visits "
        f"recalled {last['due_recalled']:.1%}, first visits recognised "
        f"{last['first_visits_recognised']:.1%}; "
        f"action classifier P {last['action_precision']:.1%} R {last['action_recall']:.1%}"
        + (" (now the policy head)" if cfg.policy_from_aux else "")
    )
    return {"config": asdict(cfg), "history": history}


def _map_of_dir(path: Path, cell_m: float | None):
    """The grid world of a run output or state directory: its grid.json, else built from its map."""
    from rl.gridmap import GridMap
    from rl.map_files import GRID_FILE, load_map_dir, write_grid

    if (path / GRID_FILE).is_file() and cell_m is None:
        return GridMap.load(path / GRID_FILE)
    grid = load_map_dir(path, **({"cell_m": cell_m} if cell_m is not None else {}))
    write_grid(path, grid)
    return grid


def _pr(res) -> str:
    return f"{100 * res.precision:.1f} / {100 * res.recall:.1f}"


def _row(policy, res, base: dict) -> list:
    grid = policy.grid
    diss = TABLE_3_1.get(grid.name)
    return [
        grid.name,
        f"{grid.shape[0]}x{grid.shape[1]}",
        grid.n_loops,
        f"{diss[0]} / {diss[1]}" if diss else "-",
        _pr(res),
        res.lc_due,
        res.lc_taken,
        f"{res.runs_complete}/{res.runs}",
        *(_pr(base[k]) if k in base else "-" for k in ("random", "no-loop-closure", "oracle")),
        policy.meta.get("steps", "-"),
        policy.meta.get("wall_s", "-"),
    ]
