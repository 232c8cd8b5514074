"""Serve a policy over a websocket: ``python -m experiments.serve --checkpoint RUN_DIR`` (or ``--export DIR``).

Compiles and warms the policy up (every batch size), then listens on ``ws://HOST:PORT`` (``127.0.0.1:8000`` by
default: localhost only; ``--host 0.0.0.0`` to serve a network, with an API key). The wire protocol is openpi's
(``hipolicy_jax/deploy/protocol.py``): the server sends the policy's manifest on connect, each observation frame
is answered with the actions to execute (the served execution strategy applied), the stride, the entropy and the
server timing; ``GET /healthz`` answers 200. Clients: ``openpi_client.websocket_client_policy.WebsocketClientPolicy``
or ``hipolicy_jax.deploy.client.PolicyClient`` (``evaluate_remote`` runs an MJX evaluation through the server).
Requests that arrive together (within ``--batch-window-ms``, up to ``--max-batch``) are decided in one call. With
``--api-key`` (or the ``HIPOLICY_API_KEY`` environment variable) a client must send ``Authorization: Api-Key
<key>``; others are refused at the handshake (HTTP 401). Bad requests get a one-line error and the server keeps
serving. Stop with Ctrl-C.
"""

from __future__ import annotations

import dataclasses
import os

from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.deploy import protocol
from hipolicy_jax.deploy.backend import ExportedBackend
from hipolicy_jax.runs.serve import run_backend
from hipolicy_jax.deploy.server import API_KEY_ENV, PolicyServer, ServerConfig
from hipolicy_jax.runs.cli import prepare_process, run_main


@dataclasses.dataclass(frozen=True)
class ServeArgs:
    checkpoint: str = ""  # run dir (holding checkpoints/) or its checkpoints/ dir; or --export
    export: str = ""  # a directory experiments.export wrote (runs without the model code)
    step: int | None = None  # checkpoint step (default: the latest)
    inference: InferenceConfig = InferenceConfig()  # --checkpoint only; default: the run's inference.json
    host: str = "127.0.0.1"  # localhost by default; 0.0.0.0 serves every interface
    port: int = 8000
    max_message_mb: float = protocol.DEFAULT_MAX_MESSAGE_BYTES / 2**20  # larger requests get an error reply
    max_batch: int = ServerConfig.max_batch  # observations decided in one call
    batch_window_ms: float = ServerConfig.batch_window_ms  # how long a request waits for others to batch with
    workers: int = ServerConfig.workers  # batches decided at the same time
    seed: int = 0  # keys of clients that send none: decision n of a connection uses fold_in(key(seed), n)
    api_key: str = ""  # required "Authorization: Api-Key <key>"; default: $HIPOLICY_API_KEY, else none


def main(args: ServeArgs) -> None:
    if bool(args.checkpoint) == bool(args.export):
        raise ValueError("checkpoint / export: pass exactly one of --checkpoint RUN_DIR and --export DIR")
    config = ServerConfig(host=args.host, port=args.port, max_message_bytes=int(args.max_message_mb * 2**20),
                          max_batch=args.max_batch, batch_window_ms=args.batch_window_ms, workers=args.workers,
                          seed=args.seed,
                          api_key=args.api_key or os.environ.get(API_KEY_ENV, ""))
    backend = ExportedBackend(args.export) if args.export else run_backend(args.checkpoint,
                                                                                        args.inference, args.step)
    server = PolicyServer(backend, config)
    if not config.api_key and args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"note: serving {args.host} without an API key (--api-key or ${API_KEY_ENV})")
    try:
        server.run()
    except KeyboardInterrupt:
        print(f"stopped after {server.requests} requests ({server.errors} errors, {server.refused} refused)")
    except OSError as e:
        raise ValueError(f"port: cannot listen on {args.host}:{args.port} ({e.strerror or e})") from None


if __name__ == "__main__":
    prepare_process()
    run_main(ServeArgs, main, __doc__)
