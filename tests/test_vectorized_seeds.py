"""Many seeds in one process (`marlmerge train --seeds`): the fused update, seed independence
and the one-seed identity bit for bit, resume after a kill, and clear errors."""

import csv
import dataclasses
import functools
import json
import subprocess
import sys

import pytest
import torch
from test_train import TINY

from marlmerge.cli import main
from marlmerge.io import files
from marlmerge.learners.common import sample_uniform
from marlmerge.learners.quadq_fast import fast_chunk
from marlmerge.learners.quadq_flat import FastSpec
from marlmerge.learners.quadq_fused import fused_chunk, fused_chunk_peaks
from marlmerge.learners.quadq_peaks import fast_chunk_peaks
from marlmerge.training.loop import make_replay
from marlmerge.training.seeds import CHECKPOINT_NAME, train_seeds
from marlmerge.training.sweep import sweep
from marlmerge.training.train import TrainConfig, load_train_config, train

SPEC = FastSpec(obs_dim=7, hidden=16, a_min=1e-3, a_span=5 - 1e-3, low=-4.5, span=7.0,
                 gamma=0.95, lr=1e-3, beta1=0.9, beta2=0.999, eps=1e-8)  # fmt: skip
P = 3 * 16 * 7 + 3 * 16 + 3 * 16 + 3


def _chunks_agree(
    single, fused, n_seeds: int, chunks: int = 3, guided: bool = False, heads: int = 3
) -> bool:
    """S seeds through `fused` against each seed through `single`, chunk after chunk: the
    weights, both Adam moments and the losses, bit for bit (with an imitation `guide` if
    `guided`; a network of `heads` heads, 3 K with K peaks)."""
    P = heads * 16 * 7 + heads * 16 + heads * 16 + heads  # noqa: N806 (the module's P)
    gen = torch.Generator().manual_seed(n_seeds)
    flat = torch.randn(n_seeds, P, generator=gen) * 0.3
    target = flat + 0.01
    m, v = torch.zeros(n_seeds, P), torch.zeros(n_seeds, P)
    alone = [(flat[j].clone(), torch.zeros(P), torch.zeros(P)) for j in range(n_seeds)]
    k = 10
    for c in range(chunks):
        steps = range(c * k + 1, (c + 1) * k + 1)
        scalars = torch.tensor([[1e-3 / (1 - 0.9**t), (1 - 0.999**t) ** 0.5] for t in steps])
        rows = torch.randn(n_seeds, k, 32, 2 * 7 + 3, generator=gen)
        rows[..., 7 + 2] = (rows[..., 7 + 2] > 1.0).float()  # some terminal transitions
        guide = torch.randn(n_seeds, k, 32, 2, generator=gen)
        guide[..., 1] = (guide[..., 1] > 0.0).float()  # imitated rows: about half
        extra = (guide,) if guided else ()
        losses, _ = fused(flat, target, m, v, scalars, rows, *extra)
        for j, (w, mj, vj) in enumerate(alone):
            loss_j = single(w, target[j], mj, vj, scalars, rows[j], *(g[j] for g in extra))
            same = [torch.equal(a, b) for a, b in ((flat[j], w), (m[j], mj), (v[j], vj))]
            if not (all(same) and torch.equal(losses[j], loss_j)):
                return False
    return True


@pytest.mark.parametrize("n_seeds", [1, 3])
def test_fused_update_is_each_seeds_own_update_bit_for_bit_eager(n_seeds):
    single = functools.partial(fast_chunk, SPEC)
    assert _chunks_agree(single, functools.partial(fused_chunk, SPEC), n_seeds)


def test_the_fused_imitation_term_is_each_seeds_own_bit_for_bit_eager():
    spec = dataclasses.replace(SPEC, imitation=0.5)
    single, fused = (functools.partial(f, spec) for f in (fast_chunk, fused_chunk))
    assert _chunks_agree(single, fused, 3, guided=True)


def test_the_fused_expectile_loss_is_each_seeds_own_bit_for_bit_eager():
    spec = dataclasses.replace(SPEC, expectile=0.25)
    single, fused = (functools.partial(f, spec) for f in (fast_chunk, fused_chunk))
    assert _chunks_agree(single, fused, 3)
    plain = functools.partial(fast_chunk, SPEC)  # and the weights change the update
    assert not _chunks_agree(plain, fused, 1, chunks=1)


@pytest.mark.parametrize(
    "options",
    [{}, {"peak_bands": True}, {"peak_share": 0.1}, {"peak_share": 0.1, "peak_share_heads": "c"},
     {"expectile": 0.25}],
    ids=["plain", "bands", "share", "share-c", "expectile"],
)  # fmt: skip
def test_fused_peaks_are_each_seeds_own_update_bit_for_bit_eager(options):
    spec = dataclasses.replace(SPEC, peaks=3, **options)
    single, fused = (functools.partial(f, spec) for f in (fast_chunk_peaks, fused_chunk_peaks))
    assert _chunks_agree(single, fused, 3, heads=9)
    other = functools.partial(fast_chunk_peaks, dataclasses.replace(spec, peaks=3, gamma=0.9))
    assert not _chunks_agree(other, fused, 1, chunks=1, heads=9)  # the check can fail


@pytest.mark.slow
def test_fused_update_is_each_seeds_own_update_bit_for_bit_compiled():
    compile_ = functools.partial(torch.compile, fullgraph=True, dynamic=False)
    single = compile_(functools.partial(fast_chunk, SPEC))
    fused = compile_(functools.partial(fused_chunk, SPEC))
    assert _chunks_agree(single, fused, 3)  # one seed: the whole-run tests below
    spec = dataclasses.replace(SPEC, peaks=3)
    single = compile_(functools.partial(fast_chunk_peaks, spec))
    fused = compile_(functools.partial(fused_chunk_peaks, spec))
    assert _chunks_agree(single, fused, 3, heads=9)


def test_fast_sampling_draws_what_the_replay_draws():
    gens = [torch.Generator().manual_seed(4) for _ in range(2)]
    a, b = (make_replay(500, g) for g in gens)
    data = torch.Generator().manual_seed(5)
    for _ in range(12):  # past the capacity: the ring wraps around
        rows = torch.randn(60, 17, generator=data)
        a.extend(rows)
        b.extend(rows)
        assert torch.equal(a.sample(320), sample_uniform(b, 320))
    assert torch.equal(gens[0].get_state(), gens[1].get_state())


def _read(path):
    with open(path, newline="") as fh:
        return list(csv.reader(fh))


def _same_run(a, b) -> None:
    """Two run folders hold the same run: logs, evaluation, selection and weights."""
    for name in ("loss.csv", "egos.csv"):
        assert _read(a / name) == _read(b / name), name
    for name in ("evaluation.json", "config.json"):
        assert (a / name).read_text() == (b / name).read_text(), name
    wa = files.load(a / "policy.pt")["policy_state"]
    wb = files.load(b / "policy.pt")["policy_state"]
    nets = [(wa["net"], wb["net"])] if "net" in wa else [(wa, wb)]
    for x, y in nets:
        for key, value in x.items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(value, y[key]), key


SMALL = {**TINY, "total_sim_steps": 3_200, "eval_episodes": 6, "eval_worlds": 3, "num_worlds": 4}


@pytest.mark.slow
@pytest.mark.parametrize(
    "algo",
    [
        {"update_path": "fast"},
        {"update_path": "compiled"},
        {"update_path": "fast", "select.every_sim_steps": 1_600, "select.episodes": 6},
        {"update_path": "fast", "lr_end_fraction": 0.1},
        {"algorithm": "dqn", "total_sim_steps": 1_600, "learning_starts": 128},
        {"update_path": "fast", "shield": "shield", "scenario": "grid_dense_adversarial"},
        {
            "update_path": "fast",
            "shield": "shield",
            "shield_penalty": 1.0,
            "scenario": "grid_dense_adversarial",
        },
        {
            "update_path": "fast",
            "shield": "shield",
            "shield_imitation": 1.0,
            "scenario": "grid_dense_adversarial",
        },
        {"update_path": "fast", "peaks": 3},
        {"update_path": "compiled", "peaks": 3},
    ],
    ids=[
        "quadq-fast",
        "quadq-compiled",
        "quadq-select",
        "quadq-lr-decay",
        "dqn",
        "quadq-shield",
        "quadq-judging",
        "quadq-imitation",
        "quadq-peaks-fast",
        "quadq-peaks-compiled",
    ],  # fmt: skip
)
def test_seeds_are_independent_and_one_seed_is_the_single_run(tmp_path, algo):
    from marlmerge.config import from_dict, to_dict
    from marlmerge.config.presets import with_overrides

    cfg = from_dict(TrainConfig, with_overrides(to_dict(TrainConfig(**SMALL)), algo))
    train_seeds(cfg, [0, 3], tmp_path / "two", progress=False)
    train(dataclasses.replace(cfg, seed=3), tmp_path / "single", progress=False)
    _same_run(tmp_path / "two" / "seed_3", tmp_path / "single")
    if cfg.update_path != "compiled":  # compiled, one seed is one more compilation (~1 min cold)
        train_seeds(cfg, [3], tmp_path / "one", progress=False)
        _same_run(tmp_path / "one" / "seed_3", tmp_path / "single")
    if cfg.shield != "none" and cfg.shield_penalty == cfg.shield_imitation == 0.0:  # behind it
        evaluation = json.loads((tmp_path / "single" / "evaluation.json").read_text())
        assert evaluation["shield_judged"] > 0 and evaluation["shield_changed_share"] is not None
    two = _read(tmp_path / "two" / "seed_0" / "egos.csv")
    assert two != _read(tmp_path / "two" / "seed_3" / "egos.csv")  # the seeds differ
    if "select.every_sim_steps" in algo:
        for run in (tmp_path / "two" / "seed_3", tmp_path / "single"):
            assert (run / "policy_last.pt").exists()
        sel = [json.loads((r / "selection.json").read_text()) for r in
               (tmp_path / "two" / "seed_3", tmp_path / "single")]  # fmt: skip
        assert sel[0] == sel[1]


@pytest.mark.slow
def test_a_killed_vectorised_run_resumes_exactly(tmp_path, capsys):
    cfg = TrainConfig(**{**SMALL, "eval_episodes": 0, "checkpoint_every_sim_steps": 1_024})
    train_seeds(cfg, [1, 2], tmp_path / "a", progress=False)
    train_seeds(cfg, [1, 2], tmp_path / "b", progress=False, stop_after_sim_steps=2_560)
    saved = files.load(tmp_path / "b" / CHECKPOINT_NAME)
    assert saved["sim_steps"] == 2_048 and saved["seeds"] == [1, 2]
    with pytest.raises(ValueError, match="already holds a run"):
        train_seeds(cfg, [1, 2], tmp_path / "b", progress=False)
    with pytest.raises(ValueError, match="trains seeds \\[1, 2\\], not \\[1, 3\\]"):
        train_seeds(cfg, [1, 3], tmp_path / "b", resume=True, progress=False)
    train_seeds(cfg, [1, 2], tmp_path / "b", resume=True, progress=False)
    for seed in (1, 2):
        a, b = tmp_path / "a" / f"seed_{seed}", tmp_path / "b" / f"seed_{seed}"
        assert _read(a / "loss.csv") == _read(b / "loss.csv")
        assert _read(a / "egos.csv") == _read(b / "egos.csv")
        wa = files.load(a / "policy.pt")["policy_state"]["net"]
        wb = files.load(b / "policy.pt")["policy_state"]["net"]
        assert all(torch.equal(wa[k], wb[k]) for k in wa)
    # the command line: resuming the finished run changes nothing
    sets = [f"--set={k}={v}" for k, v in {**SMALL, "eval_episodes": 0}.items() if k != "name"]
    sets = [s.replace("=fast", '="fast"') for s in sets]
    args = ["train", "--seeds", "1-2", "--out", str(tmp_path / "b"), "--no-progress"]
    assert main([*args, "--resume", *sets, "--set=checkpoint_every_sim_steps=1024"]) == 0
    assert "seed 2: 3,200 simulator steps" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("0-", "expected e.g. 0-9"),
        ("a", "expected e.g. 0-9"),
        ("-1", "expected e.g. 0-9"),
        ("3-1", "the range '3-1' in '3-1' is empty"),
        ("0-99999999999", "names more than 10,000 seeds"),
    ],
)
def test_bad_seed_specs_are_named(tmp_path, capsys, spec, message):
    assert main(["train", "--seeds", spec, "--out", str(tmp_path / "r"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert message in err and spec in err
    assert not (tmp_path / "r").exists()


def test_seeds_refuse_a_seed_set_and_levels_without_sample_before_any_work(tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["train", "--seeds", "0-1", "--set", "seed=3", "--out", str(out)]) == 2
    assert "--set seed=3" in capsys.readouterr().err
    args = ["train", "--seeds", "0-1", "--set", "levels.replay_fraction=0.5", "--out", str(out)]
    assert main(args) == 2
    assert "needs a scenario with [sample] ranges" in capsys.readouterr().err
    with pytest.raises(ValueError, match="rounds"):  # a co-training recipe's, too
        sweep("cotrain", [0, 1], out, {"rounds": -1}, vectorized=True, progress=False)
    assert not out.exists()


@pytest.mark.slow
def test_a_vectorised_sweep_splits_the_seeds_over_workers_and_matches_single_runs(tmp_path, capsys):
    sets = {k: v for k, v in SMALL.items() if k != "name"}
    summary = sweep(
        "paper", [0, 1, 2], tmp_path / "s", sets, "process", workers=2, vectorized=True,
        progress=False,
    )  # fmt: skip
    assert sorted(p.name for p in (tmp_path / "s").glob("seeds_checkpoint_*")) == [
        "seeds_checkpoint_0_1.pt",
        "seeds_checkpoint_2.pt",
    ]
    assert summary["groups"] == [[0, 1], [2]]  # what each process trained, in summary.json
    train(load_train_config("paper", **sets, seed=2), tmp_path / "single", progress=False)
    single = json.loads((tmp_path / "single" / "evaluation.json").read_text())
    assert json.dumps(summary["per_seed"]["2"]) == json.dumps(single)  # NaN where none merged
    _same_run(tmp_path / "s" / "seed_2", tmp_path / "single")
    with pytest.raises(ValueError, match="holds seed groups"):
        sweep("paper", [0, 1, 2], tmp_path / "s", sets, "serial", vectorized=True)
    again = sweep("paper", [0, 1, 2], tmp_path / "s", sets, "process", workers=2, vectorized=True)
    # finished groups are reused as they are
    assert json.dumps(again["per_seed"]) == json.dumps(summary["per_seed"])
    # the command says where the seeds ran
    from marlmerge.cli import main

    args = [f"--set={k}={v}" for k, v in sets.items()]
    main(["sweep", "paper", "--seeds", "0-2", "--vectorized", "--workers", "2", "--no-progress",
          "--out", str(tmp_path / "s"), *args])  # fmt: skip
    assert "3 seeds in 2 processes (0, 1; 2)" in capsys.readouterr().out


@pytest.mark.slow
def test_level_replay_seeds_are_their_single_runs(tmp_path):
    """`[levels]` with `--seeds`: each seed replays its own levels (here its own roads), and is
    its single run."""
    from test_levels import TINY as LEVELS

    cfg = load_train_config(
        "quick", **{**LEVELS, "total_sim_steps": 6_144, "levels.replay_roads": True}
    )
    train_seeds(cfg, [0, 1], tmp_path / "vec", progress=False)
    train(dataclasses.replace(cfg, seed=1), tmp_path / "one", progress=False)
    _same_run(tmp_path / "vec" / "seed_1", tmp_path / "one")
    runs = files.load(tmp_path / "vec" / CHECKPOINT_NAME)["runs"]
    single = files.load(tmp_path / "one" / "checkpoint.pt")["levels"]
    assert runs[1]["levels"] == single  # the same buffer, scores and draws
    assert runs[0]["levels"] != single
    for run in runs:  # levels were scored and replayed
        assert run["levels"]["draws"] > len(run["levels"]["levels"])
    cut = tmp_path / "cut"  # killed after a checkpoint, resumed: the level buffers come back
    train_seeds(cfg, [0, 1], cut, progress=False, stop_after_sim_steps=5_000)
    train_seeds(cfg, [0, 1], cut, resume=True, progress=False)
    for seed in (0, 1):
        _same_run(cut / f"seed_{seed}", tmp_path / "vec" / f"seed_{seed}")


@pytest.mark.slow
def test_torch_keeps_its_thread_count_after_the_batched_core_starts_numbas_pool():
    """A core of 64 worlds or more starts Numba's OpenMP pool, which resets the thread count
    torch reads too; `set_torch_threads` (what every training run calls) keeps torch's. A fresh
    process: once the pool has started, any later `torch.set_num_threads` sticks."""
    code = (
        "import torch\n"
        "from marlmerge.config import ScenarioConfig\n"
        "from marlmerge.sim.core import PARALLEL_MIN_WORLDS, TrafficCore\n"
        "from marlmerge.training.loop import set_torch_threads\n"
        "torch.get_num_threads()\n"  # torch's OpenMP runtime up first: then the pool resets it
        "set_torch_threads(1)\n"
        "core = TrafficCore(ScenarioConfig(), batch_size=PARALLEL_MIN_WORLDS, seed=0)\n"
        "core.rollout(torch.zeros(PARALLEL_MIN_WORLDS).numpy())\n"
        "print(core.parallel, torch.get_num_threads())\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=600
    )
    assert out.stdout.split()[-2:] == ["True", "1"], out.stdout + out.stderr


def _seed_slice_observations(seeds: list[int], seed: int, steps: int) -> list[torch.Tensor]:
    """Seed `seed`'s observations [B, F] of `steps` env steps in `make_seed_env(seeds)`, every
    world driving a fixed sequence of commands (the same in every grouping)."""
    from marlmerge.training.seeds import make_seed_env

    cfg = load_train_config("hardened", num_worlds=4)
    env, b, j = make_seed_env(cfg, seeds), cfg.num_worlds, seeds.index(seed)
    td, out = env.reset(), []
    for step in range(steps):
        wobble = torch.sin(torch.arange(float(b)) + 0.7 * step).repeat(len(seeds))
        td["action"] = (1.5 * wobble).unsqueeze(-1)
        _, td = env.step_and_maybe_reset(td)
        out.append(td["observation"][j * b : (j + 1) * b].clone())
    return out


def test_a_seeds_worlds_run_as_their_single_runs_whatever_the_other_seeds_do():
    """Each new road (here after every ego: `resample_every_egos = 1`) draws ahead for the next
    call and discards what its world drew for the old road; each seed's worlds are their own
    draw group, so seed 3 among 2 or 4 seeds is seed 3 alone, step for step (without groups a
    reset in another seed's world drew ahead in seed 3's and its roads drifted)."""
    alone = _seed_slice_observations([3], 3, 300)
    for seeds in ([3, 4], [0, 1, 2, 3]):
        grouped = _seed_slice_observations(seeds, 3, 300)
        diverged = [
            i for i, (a, g) in enumerate(zip(alone, grouped, strict=True)) if not torch.equal(a, g)
        ]
        assert diverged == [], f"seeds {seeds}: seed 3 differs from step {diverged[:1]}"
