"""Where one closed-loop evaluation's time goes, and the compacted rollout against the vmapped one (issue #39).

    python -m benchmarks.profile_eval                                  # profile: 20 episodes, old (vmapped) rollout
    python -m benchmarks.profile_eval --compare --episodes 100         # old vs compacted rollout, interleaved
    python -m benchmarks.profile_eval --quick                          # smoke test: tiny untrained policies

Cells: per task, the campaign's policies at the cpu budget's inference (N = 16, DDIM 10): HiPolicy with
entropy-guided chunk execution (the run's calibrated thresholds) and DP (one stride) with chunk, AAC and TE
execution (the execution table's columns). Each policy is a trained cpu-budget run when one is on disk
(``runs/paper/cpu/<task>/state/<hipolicy|dp>/seed0``, else the first ``<hipolicy|dp>_*/seed0`` variant), else an
untrained cpu-size network (``policy_source`` says which). Episodes from ``runs.store.eval_key(0)``, as the
campaign's first seed.

**Profile** (default): the pieces of the rollout, each jitted alone at the evaluation's batch (E episodes) and
timed after a warm-up with ``block_until_ready`` (median of ``--repeats`` calls): the sampler (``vmap`` of the
decision: encode, N chains, entropy, frequency), the execution strategy, one env step (physics + the task's
update; its observation timed apart), the history push, and the host side (keys, the result's transfer); the
first calls of reset, env step and sampler (compile + one run: what the rollout's compile is made of). The
rollout itself (the vmapped episode, as the campaign ran it) is then timed once; its result gives the loop's
counts (rounds of decisions = the most decisions of any episode; every round runs the sampler on all E episodes
and ``chunk_len`` env steps on all E). ``split`` = counts x piece times; ``loop bookkeeping`` = the measured
rollout minus their sum (the selects that freeze finished episodes, trace / recording writes, while / scan
overhead; negative when the pieces run slower alone than fused).

**Compare** (``--compare``): per cell the vmapped rollout (``Rollout(compact=False)``) and the compacted one
(``compact=True``, the ``Evaluator`` default) are compiled ahead of time (cold compile, timed), then run
alternately (``--rounds`` times each, old first), and their per-episode success, steps and decisions are
compared (they must be identical). Env steps/s counts the control steps the episodes executed.

**Compare drawn samples** (``--compare --all-samples``): both compacted; old: every decision draws all N
samples (as before a single-frequency policy without AAC drew sample 0 alone,
``InferenceConfig.samples_drawn``), new: today's. The per-episode outcomes are compared, as above; they are equal
unless a last-bit difference of the sampler's float32 at another batch size changes an episode.

**Compile** (``--compile``): per cell, a fresh process with an empty persistent compilation cache compiles the
Evaluator's rollout (cold), then reset, one env step and the sampler alone (in the same process, after the rollout:
they understate a cold compile of each piece, the reset most);
a second fresh process on the same cache compiles the rollout again (warm: what a campaign's next run of the same
shapes pays, ``runs.cli.enable_compilation_cache``).
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import subprocess
import sys
import tempfile
import math
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import base_parser, make_bench_policy, markdown_table, report_rows
from hipolicy_jax import envs
from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.evaluation import calibration
from hipolicy_jax.evaluation.evaluator import Evaluator
from hipolicy_jax.evaluation.execution import make_execution
from hipolicy_jax.evaluation.policy import PolicyArgs, make_decision_fn
from hipolicy_jax.evaluation.rollout import init_history, push_history, score
from hipolicy_jax.runs.store import eval_key, load_run, run_inference

NAME = "profile_eval"
CPU_INFERENCE = InferenceConfig(num_samples=16, sampler="auto", num_steps=10)  # the cpu budget's
CELLS = (("hipolicy", "chunk"), ("dp", "chunk"), ("dp", "aac"), ("dp", "te"))


def parse_args(argv=None):
    p = base_parser(NAME, __doc__)
    p.add_argument("--tasks", nargs="+", default=["press_button", "pick_place"])
    p.add_argument("--cells", nargs="+", default=[f"{k}:{e}" for k, e in CELLS],
                   help="policy:execution pairs (policy hipolicy | dp; execution chunk | aac | te)")
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--runs", default="runs/paper/cpu", help="where the campaign's cpu-budget runs are")
    p.add_argument("--repeats", type=int, default=3, help="timed calls per piece")
    p.add_argument("--compare", action="store_true", help="old (vmapped) vs compacted rollout, interleaved")
    p.add_argument("--rounds", type=int, default=1, help="--compare: timed rollouts per path (after the compile)")
    p.add_argument("--compile", action="store_true", help="cold and warm-cache compile times of the rollout")
    p.add_argument("--compile-child", default=None, help=argparse.SUPPRESS)  # cache dir of a --compile process
    p.add_argument("--full-forward-reset", action="store_true",
                   help="--compile: also compile the rollout as it was before the kinematic reset (the reset runs "
                        "the full mjx.forward), cold and warm, interleaved with today's")
    p.add_argument("--all-samples", action="store_true",
                   help="--compare: old = every decision draws all N samples (before single-frequency decisions "
                        "without AAC drew sample 0 alone), new = today's; both compacted")
    p.add_argument("--block", type=int, default=None, help="--compare: episodes per block (default: the Evaluator's)")
    p.add_argument("--max-steps", type=int, default=None, help="cap the episodes (default: the task's limit)")
    p.add_argument("--tag", default="", help="appended to the JSON's name (profile_eval[_compare][_TAG]_<device>)")
    p.add_argument("--quick", action="store_true", help="tiny untrained policies, 4 episodes, 16 steps, N 4, DDIM 2")
    args = p.parse_args(argv)
    if args.quick:
        args.tasks, args.episodes, args.max_steps, args.repeats = args.tasks[:1], 4, 16, 1
    return args


def find_run(root: str, task: str, kind: str) -> str | None:
    """The trained run of ``kind`` (hipolicy | dp) on ``task``: ``<kind>/seed0``, else the first ``<kind>_*/seed0``
    variant with checkpoints; None when there is none."""
    base = os.path.join(root, task, "state")
    for d in [os.path.join(base, kind, "seed0"), *sorted(glob.glob(os.path.join(base, f"{kind}_*", "seed0")))]:
        if os.path.isdir(os.path.join(d, "checkpoints")) and os.listdir(os.path.join(d, "checkpoints")):
            return d
    return None


def load_policy(args, task: str, kind: str, execution: str):
    """(cfg, net, action_dim, PolicyArgs, InferenceConfig, source) of the cell's policy."""
    env = envs.make(task)
    run_dir = None if args.quick else find_run(args.runs, task, kind)
    if run_dir is not None:
        run = load_run(run_dir)
        inference = dataclasses.replace(run_inference(run, CPU_INFERENCE), execution=execution)
        cfg, p = run.policy.cfg, run.policy
        thresholds = None
        if kind == "hipolicy" and cfg.chunk.num_freqs > 1:
            thresholds = calibration.resolve_thresholds(inference, cfg.chunk.num_freqs,
                                                        calibration.read_calibration(run.run_dir))[0]
        th = calibration.guidance_thresholds(thresholds, cfg.chunk.num_freqs, thresholds is not None)
        source = f"trained: {os.path.relpath(run_dir)} step {p.step}"
        return cfg, p.net, run.action_dim, PolicyArgs(p.params, p.normalizer, th), inference, source
    size = "tiny" if args.quick else "cpu"
    changes = {"chunk.strides": (1,)} if kind == "dp" else {}
    pol = make_bench_policy(size, "state", state_dim=env.state_dim, action_dim=env.action_dim, **changes)
    inference = (InferenceConfig(num_samples=4, sampler="ddim", num_steps=2, execution=execution) if args.quick
                 else dataclasses.replace(CPU_INFERENCE, execution=execution))
    th = calibration.guidance_thresholds(None, pol.cfg.chunk.num_freqs, False)
    return pol.cfg, pol.net, env.action_dim, PolicyArgs(pol.params, pol.normalizer, th), inference, \
        f"untrained {size}-size network (no trained run on disk)"


def timed(fn, *a, repeats: int = 3, first: dict | None = None, name: str = "") -> float:
    """Median seconds of ``fn(*a)`` (block_until_ready) after one warm-up call (its seconds, compile included, go
    to ``first[name]``)."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*a))
    if first is not None:
        first[name] = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*a))
        times.append(time.perf_counter() - t0)
    return float(np.median(times)) if times else math.nan


def piece_times(ev: Evaluator, net, cfg, action_dim, pargs, inference, batch: int, repeats: int) -> dict:
    """ms per call of each rollout piece, jitted alone at ``batch`` episodes."""
    env = ev.env
    keys = jax.random.split(jax.random.key(0), batch)
    states = jax.jit(jax.vmap(env.reset))(keys)
    hist = jax.jit(jax.vmap(lambda o: init_history(o, cfg.chunk.obs_span)))(states.obs)
    decide = jax.jit(jax.vmap(make_decision_fn(net, cfg, action_dim, inference), in_axes=(0, 0, None)))
    execution = make_execution(inference)
    estate = jax.vmap(lambda _: execution.init(cfg.chunk, action_dim))(keys)
    d = decide(hist, keys, pargs)
    exec_fn = jax.jit(jax.vmap(lambda d, s: execution.decide(d, s, cfg.chunk)))
    actions = jnp.concatenate([states.obs["state"][:, :3], jnp.zeros((batch, 1))], axis=1)  # hold the hand still
    step = jax.jit(jax.vmap(env.step))
    observe = jax.jit(jax.vmap(lambda s: env._observe(env.episode_model(s.info), s.data, s.info)))
    push = jax.jit(jax.vmap(push_history))
    first: dict = {}
    timed(jax.jit(jax.vmap(env.reset)), keys, repeats=0, first=first, name="reset")
    out = {"sampler_ms": timed(decide, hist, keys, pargs, repeats=repeats, first=first, name="sampler"),
           "execution_ms": timed(exec_fn, d, estate, repeats=repeats),
           "env_step_ms": timed(step, states, actions, repeats=repeats, first=first, name="env_step"),
           "observation_ms": timed(observe, states, repeats=repeats),
           "history_ms": timed(push, hist, states.obs, repeats=repeats)}
    out["physics_ms"] = out["env_step_ms"] - out["observation_ms"]
    return {**{k: v * 1e3 for k, v in out.items()}, "first_call_s": first}


def outcome(res) -> dict:
    valid = np.asarray(res.valid)
    return {"success": [bool(x) for x in np.asarray(res.success)], "steps": [int(x) for x in np.asarray(res.steps)],
            "decisions": [int(x) for x in valid.sum(axis=1)]}


def rounds_of(decisions: list[int], block: int) -> tuple[int, int]:
    """(rounds of decisions, blocks the compacted rollout runs over all rounds)."""
    dec = np.asarray(decisions)
    rounds = int(dec.max())
    return rounds, int(sum(math.ceil((dec > r).sum() / block) for r in range(rounds)))


def profile_cell(args, task: str, kind: str, execution: str) -> dict:
    cfg, net, action_dim, pargs, inference, source = load_policy(args, task, kind, execution)
    ev = Evaluator(task, cfg, action_dim, inference, max_steps=args.max_steps, compact=False)
    e, lc = args.episodes, make_execution(inference).exec_len(cfg.chunk)
    print(f"[{task} {kind} {execution}] {source}", flush=True)
    pieces = piece_times(ev, net, cfg, action_dim, pargs, inference, e, args.repeats)
    ro = ev._rollout
    keys = jax.device_put(jax.random.split(eval_key(0), e))
    t0 = time.perf_counter()
    compiled = ro._jitted.lower(keys, pargs).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    state, trace, rec = jax.block_until_ready(compiled(keys, pargs))
    rollout_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    host = jax.device_get((score(state, trace), rec))
    transfer_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(jax.device_put(jax.random.split(eval_key(0), e)))
    keys_s = time.perf_counter() - t0
    res = host[0]
    oc = outcome(res)
    rounds = max(oc["decisions"])
    split = {"sampler": rounds * pieces["sampler_ms"] / 1e3, "execution": rounds * pieces["execution_ms"] / 1e3,
             "physics + task": rounds * lc * pieces["physics_ms"] / 1e3,
             "observation": rounds * lc * pieces["observation_ms"] / 1e3,
             "history": rounds * lc * pieces["history_ms"] / 1e3, "host (keys, result transfer)": transfer_s + keys_s}
    split["loop bookkeeping"] = rollout_s + keys_s + transfer_s - sum(split.values())
    total = rollout_s + keys_s + transfer_s
    steps = int(np.sum(oc["steps"]))
    row = {"task": task, "policy": kind, "execution": execution, "policy_source": source, "episodes": e,
           "chunk_len": lc, "num_samples": inference.num_samples, "sampler": inference.sampler,
           "num_steps": inference.num_steps, "max_steps": ev._rollout.max_steps or ev.env.max_steps,
           "pieces_ms": pieces, "rounds": rounds, "env_step_calls": rounds * lc, "control_steps": steps,
           "useful_fraction": steps / (rounds * lc * e), "decisions_total": int(sum(oc["decisions"])),
           "decision_fraction": sum(oc["decisions"]) / (rounds * e), "compile_s": compile_s,
           "rollout_s": rollout_s, "total_s": total, "env_steps_per_s": steps / total, "split_s": split,
           "split_pct": {k: 100.0 * v / total for k, v in split.items()},
           "success_rate": float(np.mean(oc["success"])), **oc}
    print(f"  rollout {rollout_s:.1f} s (compile {compile_s:.1f} s), {rounds} rounds, {steps} control steps "
          f"({100 * row['useful_fraction']:.0f} % of the env steps run), "
          + ", ".join(f"{k} {v:.0f}%" for k, v in row["split_pct"].items()), flush=True)
    return row


def compile_times(args, task: str, kind: str, execution: str, pieces: bool) -> dict:
    """In this process (its cache: ``args.compile_child``): seconds to compile the Evaluator's rollout, and with
    ``pieces`` then reset, one env step and the sampler alone (batched over the episodes)."""
    jax.config.update("jax_compilation_cache_dir", args.compile_child)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    if args.full_forward_reset:  # this child process only: the reset as before 711be2f (a full forward pass)
        from mujoco import mjx
        mjx.kinematics = mjx.forward
    cfg, net, action_dim, pargs, inference, source = load_policy(args, task, kind, execution)
    ev = Evaluator(task, cfg, action_dim, inference, max_steps=args.max_steps)
    ro, e = ev._rollout, args.episodes
    keys = jax.device_put(jax.random.split(eval_key(0), e))

    def seconds(lower):
        t0 = time.perf_counter()
        lower().compile()
        return time.perf_counter() - t0

    out = {"policy_source": source, "rollout_s": seconds(lambda: ro._compacted.lower(keys, pargs, ro.block_for(e)))}
    if pieces:
        env = ev.env
        states = jax.jit(jax.vmap(env.reset))(keys)
        hist = jax.vmap(lambda o: init_history(o, cfg.chunk.obs_span))(states.obs)
        actions = jnp.zeros((e, env.action_dim), jnp.float32)
        decide = jax.vmap(make_decision_fn(net, cfg, action_dim, inference), in_axes=(0, 0, None))
        out.update(reset_s=seconds(lambda: jax.jit(jax.vmap(env.reset)).lower(keys)),
                   env_step_s=seconds(lambda: jax.jit(jax.vmap(env.step)).lower(states, actions)),
                   sampler_s=seconds(lambda: jax.jit(decide).lower(hist, keys, pargs)))
    return out


def compile_cell(args, task: str, kind: str, execution: str) -> dict:
    """Cold (empty cache, pieces too) and warm-cache compile of the cell's rollout, each in a fresh process; with
    ``--full-forward-reset`` the same for the rollout whose reset runs the full forward dynamics (before), today's
    and before's processes alternating."""
    print(f"[{task} {kind} {execution}] compile", flush=True)
    variants = ("after", "before") if args.full_forward_reset else ("after",)
    out = {}
    with tempfile.TemporaryDirectory() as root:
        caches = {v: os.path.join(root, v) for v in variants}
        for cache in caches.values():
            os.makedirs(cache)
        for stage in ("cold", "warm"):
            for variant in variants:
                cmd = [sys.executable, "-m", "benchmarks.profile_eval", "--compile-child", caches[variant], "--tasks",
                       task, "--cells", f"{kind}:{execution}", "--episodes", str(args.episodes), "--runs", args.runs,
                       *(["--max-steps", str(args.max_steps)] if args.max_steps else []),
                       *(["--quick"] if args.quick else []),
                       *(["--full-forward-reset"] if variant == "before" else [])]
                proc = subprocess.run(cmd, capture_output=True, text=True, check=True)
                out[variant, stage] = json.loads(proc.stdout.strip().splitlines()[-1])
    cold = out["after", "cold"]
    row = {"task": task, "policy": kind, "execution": execution, "episodes": args.episodes,
           "policy_source": cold["policy_source"], "cold_s": cold["rollout_s"],
           "warm_cache_s": out["after", "warm"]["rollout_s"],
           **{f"{k}_alone_s": cold[f"{k}_s"] for k in ("reset", "env_step", "sampler")}}
    if args.full_forward_reset:
        row.update(before_cold_s=out["before", "cold"]["rollout_s"], before_warm_cache_s=out["before", "warm"]["rollout_s"],
                   before_reset_alone_s=out["before", "cold"]["reset_s"])
    print(f"  rollout cold {row['cold_s']:.1f} s (reset {row['reset_alone_s']:.1f}, env step "
          f"{row['env_step_alone_s']:.1f}, sampler {row['sampler_alone_s']:.1f} s alone), warm cache "
          f"{row['warm_cache_s']:.1f} s" + (f"; before: cold {row['before_cold_s']:.1f} s, warm cache "
                                            f"{row['before_warm_cache_s']:.1f} s" if args.full_forward_reset else ""),
          flush=True)
    return row


def compare_cell(args, task: str, kind: str, execution: str) -> dict:
    cfg, net, action_dim, pargs, inference, source = load_policy(args, task, kind, execution)
    e = args.episodes
    print(f"[{task} {kind} {execution}] {source}, {e} episodes", flush=True)
    paths = {}
    for name in ("old", "new"):
        compact = args.all_samples or name == "new"
        if args.all_samples and name == "old":  # this evaluator only: a decision draws all N samples
            drawn = InferenceConfig.samples_drawn
            InferenceConfig.samples_drawn = lambda self, num_freqs: self.num_samples
            try:
                ev = Evaluator(task, cfg, action_dim, inference, max_steps=args.max_steps, compact=compact)
            finally:
                InferenceConfig.samples_drawn = drawn
        else:
            ev = Evaluator(task, cfg, action_dim, inference, max_steps=args.max_steps, compact=compact)
        ro = ev._rollout
        if args.block:
            ro.block = args.block
        keys = jax.device_put(jax.random.split(eval_key(0), e))
        block = ro.block_for(e)
        t0 = time.perf_counter()
        compiled = (ro._compacted.lower(keys, pargs, block) if compact else ro._jitted.lower(keys, pargs)).compile()
        paths[name] = {"compiled": compiled, "keys": keys, "block": block, "samples": ro.rows_per_episode,
                       "compile_s": time.perf_counter() - t0, "times": [], "outcomes": []}
    for _ in range(args.rounds):
        for name in ("old", "new"):
            p = paths[name]
            t0 = time.perf_counter()
            state, trace, rec = jax.block_until_ready(p["compiled"](p["keys"], pargs))
            p["times"].append(time.perf_counter() - t0)
            p["outcomes"].append(outcome(jax.device_get(score(state, trace))))
            print(f"  {name}: {p['times'][-1]:.1f} s", flush=True)
    old, new = paths["old"], paths["new"]
    identical = all(o == old["outcomes"][0] for p in (old, new) for o in p["outcomes"])
    oc = old["outcomes"][0]
    steps = int(np.sum(oc["steps"]))
    rounds, blocks = rounds_of(oc["decisions"], new["block"])
    t_old, t_new = float(np.median(old["times"])), float(np.median(new["times"]))
    row = {"task": task, "policy": kind, "execution": execution, "policy_source": source, "episodes": e,
           "num_samples": inference.num_samples, "old_samples_drawn": old["samples"],
           "new_samples_drawn": new["samples"], "block": new["block"], "old_block": old["block"], "rounds": rounds,
           "blocks_run": blocks, "episode_decisions_old": rounds * e, "episode_decisions_new": blocks * new["block"],
           "decisions": int(sum(oc["decisions"])), "control_steps": steps,
           "old_s": t_old, "new_s": t_new, "old_times_s": old["times"], "new_times_s": new["times"],
           "speedup": t_old / t_new, "old_env_steps_per_s": steps / t_old, "new_env_steps_per_s": steps / t_new,
           "old_compile_s": old["compile_s"], "new_compile_s": new["compile_s"], "identical_outcomes": identical,
           "success_rate": float(np.mean(oc["success"])), "old": old["outcomes"][0], "new": new["outcomes"][0]}
    print(f"  speedup {row['speedup']:.2f}x ({t_old:.1f} -> {t_new:.1f} s), env steps/s "
          f"{row['old_env_steps_per_s']:.0f} -> {row['new_env_steps_per_s']:.0f}, compile {old['compile_s']:.1f} / "
          f"{new['compile_s']:.1f} s, identical outcomes: {identical}", flush=True)
    return row


def _span(values, fmt="{:.0f}") -> str:
    lo, hi = min(values), max(values)
    return fmt.format(lo) if fmt.format(lo) == fmt.format(hi) else f"{fmt.format(lo)}–{fmt.format(hi)}"


def profile_note(rows: list[dict]) -> str:
    """The profile's figures in words, every number from ``rows``."""
    pct = lambda part: [r["split_pct"][part] for r in rows]  # noqa: E731
    small = [sum(r["split_pct"][p] for p in SMALL_PARTS) for r in rows]
    aac = [r for r in rows if r["execution"] == "aac"]
    first = [r["pieces_ms"]["first_call_s"] for r in rows]
    lines = [
        f"{rows[0]['episodes']} episodes per cell, N = {rows[0]['num_samples']}, sampler {rows[0]['sampler']} with "
        f"{rows[0]['num_steps']} steps, the vmapped rollout (as the campaigns' records were made); other jobs ran at "
        f"nice 19 (load average in the JSON's `machine`). Percentages: counts x the pieces' times alone over the "
        f"measured rollout, so they need not add up to 100 (a piece jitted alone can run slower than fused in the "
        f"rollout: then loop bookkeeping is negative). Policies: "
        + "; ".join(sorted({f"{r['task']} {r['policy']}: {r['policy_source']}" for r in rows})) + ".",
        "",
        f"- **The sampler is the evaluation**: {_span(pct('sampler'))} % (median "
        f"{float(np.median(pct('sampler'))):.0f} %) of the rollout (its time alone x the rounds "
        f"of decisions). Physics + the task's update {_span(pct('physics + task'))} % (pick_place's contacts cost "
        f"the most); observation, history, execution strategy and host transfers together "
        f"{_span(small, '{:.1f}')} %.",
        f"- **Every round runs the sampler for all E episodes**, finished or not: the decisions the episodes took "
        f"are {_span([100 * r['decision_fraction'] for r in rows])} % of the sampler rows the rollout computes, "
        f"and {_span([100 * r['useful_fraction'] for r in rows])} % of the env steps it runs are executed "
        f"control steps" + (f" (AAC: {_span([100 * r['useful_fraction'] for r in aac])} %, a round runs L_c masked "
                            f"steps for decisions of fewer actions)" if aac else "") + ".",
        f"- **Compile**: {_span([r['compile_s'] for r in rows])} s a rollout, nearly all MJX: the first call of "
        f"the batched reset takes {_span([f['reset'] for f in first])} s and of one env step "
        f"{_span([f['env_step'] for f in first])} s (compile + one run).",
    ]
    return "\n".join(lines)


SMALL_PARTS = ("execution", "observation", "history", "host (keys, result transfer)")


def profile_table(rows: list[dict]) -> str:
    return markdown_table(
        ["task", "policy", "execution", "success %", "rollout s", "env steps/s", "rounds", "executed / run env steps %",
         "sampler %", "physics + task %", "obs., history, execution, host %", "loop bookkeeping %",
         "sampler s / round", "env step ms", "compile s"],
        [[r["task"], r["policy"], r["execution"], 100 * r["success_rate"], r["total_s"], r["env_steps_per_s"],
          r["rounds"], 100 * r["useful_fraction"], r["split_pct"]["sampler"], r["split_pct"]["physics + task"],
          sum(r["split_pct"][p] for p in SMALL_PARTS), r["split_pct"]["loop bookkeeping"],
          r["pieces_ms"]["sampler_ms"] / 1e3, r["pieces_ms"]["env_step_ms"], r["compile_s"]] for r in rows])


def compare_note(rows: list[dict]) -> str:
    """The comparison's figures in words, every number from ``rows``. The sampler is ~100 % of a rollout (the
    profile), so the compacted rollout gains about the sampler rows the vmapped one computes over those it computes
    itself (``episode_decisions_old / episode_decisions_new``); skipped physics (finished episodes, AAC's early
    exit) adds a little."""
    def same(r, keys):
        return all(r["old"][k] == r["new"][k] for k in keys)

    outcome_rows = [r for r in rows if same(r, ("success", "steps"))]
    differ = [f"{r['task']} {r['policy']} {r['execution']}" for r in rows if not same(r, ("success", "steps", "decisions"))]
    drawn = rows[0].get("old_samples_drawn", 0) != rows[0].get("new_samples_drawn", 0)
    if drawn:
        what = ("Old: every decision draws all N samples; new: a single-frequency decision without AAC draws sample 0 "
                "alone (`InferenceConfig.samples_drawn`); both compacted rollouts.")
        ratio = ("the sampler's rows per decision (old / new)", lambda r: r["old_samples_drawn"] / r["new_samples_drawn"])
    else:
        what = ("Old: the vmapped episode (`Rollout(compact=False)`); new: the compacted rollout (`compact=True`, the "
                "Evaluator's default).")
        ratio = ("the ratio of sampler rows the two compute (old / new)",
                 lambda r: r["episode_decisions_old"] / r["episode_decisions_new"])
    lines = [
        f"{what} Both compiled ahead of time, then run alternately (old first), "
        f"{rows[0]['episodes']} episodes from the campaign's first evaluation key; other jobs ran at nice 19 (load "
        f"average in the JSON's `machine`).",
        "",
        f"- Speedup (old s / new s) against {ratio[0]}: "
        + ", ".join(f"{r['task']} {r['policy']} {r['execution']} {r['speedup']:.2f}x of {ratio[1](r):.2f}x "
                    f"({r['old_s']:.0f} → {r['new_s']:.0f} s)" for r in rows) + ".",
        f"- Per-episode success and steps identical in {len(outcome_rows)} of {len(rows)} cells; success, steps "
        f"and decisions in {len(rows) - len(differ)}"
        + (f" (decisions differ: {', '.join(differ)}; blocks run the sampler at another batch size, whose float32 "
           f"rounding differs in the last bits)." if differ else "."),
        f"- Cold compile old / new: {_span([r['old_compile_s'] for r in rows])} s / "
        f"{_span([r['new_compile_s'] for r in rows])} s.",
    ]
    return "\n".join(lines)


def main(argv=None) -> dict:
    args = parse_args(argv)
    cells = [tuple(c.split(":")) for c in args.cells]
    if args.compile_child is not None:  # one process of --compile: one cell, its figures on stdout's last line
        (kind, execution), = cells
        first = not os.listdir(args.compile_child)
        print(json.dumps(compile_times(args, args.tasks[0], kind, execution, pieces=first)))
        return {}
    if args.compile:
        rows = [compile_cell(args, task, kind, execution) for task in args.tasks for kind, execution in cells]
        before = args.full_forward_reset
        table = markdown_table(
            ["task", "policy", "execution", "episodes", "rollout cold s", "reset alone s", "env step alone s",
             "sampler alone s", "rollout warm cache s"]
            + (["before: cold s", "before: reset alone s", "before: warm cache s"] if before else []),
            [[r["task"], r["policy"], r["execution"], r["episodes"], r["cold_s"], r["reset_alone_s"],
              r["env_step_alone_s"], r["sampler_alone_s"], r["warm_cache_s"]]
             + ([r["before_cold_s"], r["before_reset_alone_s"], r["before_warm_cache_s"]] if before else [])
             for r in rows])
        return report_rows(NAME + "_compile" + (f"_{args.tag}" if args.tag else ""), argv, args, rows, table,
                           module=NAME)
    rows = []
    for task in args.tasks:
        for kind, execution in cells:
            rows.append((compare_cell if args.compare else profile_cell)(args, task, kind, execution))
    if args.compare:
        table = markdown_table(
            ["task", "policy", "execution", "episodes", "block", "old s", "new s", "speedup", "env steps/s old",
             "env steps/s new", "episode-decisions old / new", "compile s old / new", "identical outcomes"],
            [[r["task"], r["policy"], r["execution"], r["episodes"], r["block"], r["old_s"], r["new_s"],
              f"{r['speedup']:.2f}x", r["old_env_steps_per_s"], r["new_env_steps_per_s"],
              f"{r['episode_decisions_old']} / {r['episode_decisions_new']}",
              f"{r['old_compile_s']:.1f} / {r['new_compile_s']:.1f}", r["identical_outcomes"]] for r in rows])
        return report_rows(NAME + "_compare" + (f"_{args.tag}" if args.tag else ""), argv, args, rows, table,
                           module=NAME, note=compare_note(rows))
    return report_rows(NAME + (f"_{args.tag}" if args.tag else ""), argv, args, rows, profile_table(rows),
                       module=NAME, note=profile_note(rows))


if __name__ == "__main__":
    main()
