"""Benchmarks of the library's stages: what sampling, training, evaluation and serving cost on this machine.

Not a stage of the data flow (data → encoders → denoiser → generative head → sampling → evaluation →
experiments) but a measurement of it: each module is a command, ``python -m benchmarks.<name> --help``, that times
the library's own code on benchmark policies (``common.make_bench_policy``: untrained networks of the ``tiny`` /
``cpu`` / ``paper`` sizes, or the PyTorch comparison's shapes, ``common.SHAPES``) or on trained runs, prints a
markdown table and writes ``benchmarks/results/<name>_<device>.json``.

The benchmarks a user runs:

- ``sampling``: one-call N-sample latency, memory and GFLOP/s of the sampler (the paper's sample-times table);
- ``train_step``: train-step throughput and compile time;
- ``rollout``: closed-loop MJX rollout throughput with the policy in the loop;
- ``tradeoff``: decision latency against closed-loop success per sampler setting of trained runs;
- ``delay``: closed-loop success under inference delay (asynchronous execution, naive vs inpainting hand-over);
- ``serving``: in-process, exported and websocket decisions, and load tests of the policy server;
- ``profile``: where the sampler's and the train step's time goes, per model part (a ``jax.profiler`` trace);
- ``profile_eval``: where one closed-loop evaluation's time goes; the compacted rollout against the vmapped one;
- ``roofline``: the train step stage by stage (encoder, denoiser, optimizer) against the machine's measured matmul
  peak and bandwidth, for point-cloud and image policies.

``benchmarks.studies`` holds the finished before / after studies, whose answers PERFORMANCE.md states (their JSON
in ``benchmarks/studies/results/``). Shared pieces: ``common`` (benchmark policies, timing, FLOPs, machine peaks,
JSON output), ``machine`` (the CPU model, cores, load and peaks every JSON records) and ``report``
(``python -m benchmarks.report --notes benchmarks/results/notes_cpu.md`` assembles
``benchmarks/results/PERFORMANCE.md`` from the JSONs and the notes).
"""

from hipolicy_jax.host_memory import keep_freed_memory

# A benchmark measures what an entry point's process does (``runs.cli.prepare_process``): glibc keeps freed memory.
# Importing this package sets it, before any benchmark's first JAX computation.
keep_freed_memory()
