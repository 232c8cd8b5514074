"""Serve a policy over a websocket: ``python -m experiments.serve --checkpoint RUN_DIR`` (or ``--export DIR``).

Compiles and warms the policy up, then listens on ``ws://HOST:PORT`` (``127.0.0.1:8000`` by default: localhost
only; ``--host 0.0.0.0`` to serve a network). Each request (an observation history, msgpack) is answered with the
chunk, the selected stride, the entropy and the server-side latency; ``metadata`` and ``health`` requests describe
the policy and the server; bad requests get an error reply naming the problem and the server keeps serving.
Clients: ``hipolicy_jax.deploy.client.PolicyClient`` (``evaluate_remote`` runs an MJX evaluation through the
server). Messages are described in ``hipolicy_jax/deploy/protocol.py``. Stop with Ctrl-C.
"""

from __future__ import annotations

import dataclasses

from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.deploy import protocol
from hipolicy_jax.deploy.backend import ExportedBackend, InProcessBackend
from hipolicy_jax.deploy.server import PolicyServer
from hipolicy_jax.runs.cli import enable_compilation_cache, run_main


@dataclasses.dataclass(frozen=True)
class ServeArgs:
    checkpoint: str = ""  # run dir (holding checkpoints/) or its checkpoints/ dir; or --export
    export: str = ""  # a directory experiments.export wrote (runs without the model code)
    step: int | None = None  # checkpoint step (default: the latest)
    inference: InferenceConfig = InferenceConfig()  # --checkpoint only; default: the run's inference.json
    host: str = "127.0.0.1"  # localhost by default; 0.0.0.0 serves every interface
    port: int = 8000
    max_message_mb: float = protocol.DEFAULT_MAX_MESSAGE_BYTES / 2**20  # larger requests get an error reply
    max_batch: int = protocol.DEFAULT_MAX_BATCH  # observation histories per request


def main(args: ServeArgs) -> None:
    if bool(args.checkpoint) == bool(args.export):
        raise ValueError("checkpoint / export: pass exactly one of --checkpoint RUN_DIR and --export DIR")
    backend = ExportedBackend(args.export) if args.export else InProcessBackend.from_run(args.checkpoint,
                                                                                        args.inference, args.step)
    server = PolicyServer(backend, args.host, args.port, max_message_bytes=int(args.max_message_mb * 2**20),
                          max_batch=args.max_batch)
    try:
        server.run()
    except KeyboardInterrupt:
        print(f"stopped after {server.requests} requests ({server.errors} errors)")
    except OSError as e:
        raise ValueError(f"port: cannot listen on {args.host}:{args.port} ({e.strerror or e})") from None


if __name__ == "__main__":
    enable_compilation_cache()
    run_main(ServeArgs, main, __doc__)
