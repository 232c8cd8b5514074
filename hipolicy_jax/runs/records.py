"""Run records and the network they describe: one trained network per record.

A record (``campaign.Campaign``) keeps a run's configs, training summary and calibration and, per evaluation, the
per-episode outcomes. Version 2 adds **the network**: ``record["network"]`` is the fingerprint of the network the
record describes now, and every evaluation carries the fingerprint of the network it evaluated:

    {"params_sha256": <SHA-256 of the EMA parameters, or None>, "final_loss": <mean loss of the last 50 steps>}

``record["evaluations"]`` only ever holds evaluations of ``record["network"]``. When a run is retrained (its
checkpoint was not on the machine) and the new network differs, every evaluation of the old one moves to
``record["superseded"]`` (kept, with its network, never read by a table) and the campaign evaluates the new
network afresh: a paired comparison inside one run (HiPolicy with vs without entropy guidance, DP vs DP+TE) then
always compares one network with itself.

Identity: two fingerprints are the same network when both have a parameter hash and the hashes are equal; a
version-1 evaluation has no hash (its parameters are gone), only the final loss of the training it came from,
read from the record's git history (``git_first_losses``). A float64 mean of 50 float32 losses equal to the last
bit is taken as the same training; a loss that differs in any bit is another network. Retraining reproduces the
hash on one machine (XLA's CPU kernels are deterministic there) but not across CPU models: the same config
retrained on another CPU gives losses that differ from the 9th digit on (``results/PROTOCOL.md`` v2).
"""

from __future__ import annotations

import copy
import json
import os
import subprocess

from hipolicy_jax.checkpoint import tree_sha256

RECORD_VERSION = 2


def params_fingerprint(params) -> str:
    """SHA-256 of a parameter pytree: every leaf's path, dtype, shape and bytes, in path order (the checksum a
    checkpoint stores for its trees, ``checkpoint.tree_sha256``)."""
    return tree_sha256(params)


def network(params, final_loss: float | None) -> dict:
    """The fingerprint of a trained network: its EMA parameters' hash and its final training loss."""
    return {"params_sha256": params_fingerprint(params),
            "final_loss": None if final_loss is None else float(final_loss)}


def same_network(a: dict | None, b: dict | None) -> bool:
    """Whether two fingerprints name one network: the parameter hashes when both have one, else the final losses
    (equal to the bit; a missing loss matches nothing)."""
    if not a or not b:
        return False
    if a.get("params_sha256") and b.get("params_sha256"):
        return a["params_sha256"] == b["params_sha256"]
    return a.get("final_loss") is not None and a.get("final_loss") == b.get("final_loss")


def merged(a: dict, b: dict) -> dict:
    """The fingerprint of one network known by two fingerprints (``same_network(a, b)``): the hash either has."""
    return {"params_sha256": a.get("params_sha256") or b.get("params_sha256"),
            "final_loss": a.get("final_loss") if a.get("final_loss") is not None else b.get("final_loss")}


def supersede(record: dict, net: dict) -> dict:
    """``record`` describing ``net``: evaluations of any other network move to ``superseded`` (one entry per
    network, with the training summary and calibration they came with); ``network`` becomes ``net``."""
    out = copy.deepcopy(record)
    old = out.get("network")
    keep, moved = {}, {}
    for key, ev in out.get("evaluations", {}).items():
        (keep if same_network(ev.get("network"), net) else moved)[key] = ev
    groups: list[tuple[dict | None, dict]] = []  # the moved evaluations by the network each was made on
    for key, ev in moved.items():
        net_of = ev.get("network") or old
        for known, evs in groups:
            if known == net_of:
                evs[key] = ev
                break
        else:
            groups.append((net_of, {key: ev}))
    for net_of, evs in groups:
        entry = {"network": net_of, "evaluations": evs}
        if same_network(net_of, old):  # the training summary and calibration the record held were this network's
            entry = {"network": net_of, "training": out.get("training"), "calibration": out.get("calibration"),
                     "evaluations": evs}
        out["superseded"] = [*out.get("superseded", []), entry]
    out["evaluations"] = keep
    out["network"] = merged(net, old) if same_network(old, net) else dict(net)
    return out


def problems(record: dict) -> list[str]:
    """What breaks the one-network rule in a record (empty when it holds): a missing network, or an evaluation of
    another network than the record's."""
    if record.get("version", 1) < RECORD_VERSION:
        return [f"version {record.get('version', 1)} (< {RECORD_VERSION}): no network fingerprints"]
    net = record.get("network")
    if not net:
        return ["no 'network'"]
    return [f"evaluation {json.loads(k).get('execution')}/guided={json.loads(k).get('guided')}/"
            f"percentiles={json.loads(k).get('percentiles')} is of network {ev.get('network')}, the record's is {net}"
            for k, ev in record.get("evaluations", {}).items() if not same_network(ev.get("network"), net)]


def upgrade_v1(record: dict, first_losses: dict[str, float]) -> dict:
    """A version-1 record as version 2: each evaluation's network is the final loss of the training it was made
    on (``first_losses``: the record's ``training.final_loss`` when the evaluation first appeared in git; the
    current one when git does not know it), no parameter hash; evaluations of an earlier training move to
    ``superseded``."""
    if record.get("version", 1) >= RECORD_VERSION:
        return record
    current = {"params_sha256": None, "final_loss": (record.get("training") or {}).get("final_loss")}
    out = copy.deepcopy(record)
    for key, ev in out.get("evaluations", {}).items():
        ev["network"] = {"params_sha256": None, "final_loss": first_losses.get(key, current["final_loss"])}
    out["version"] = RECORD_VERSION
    out["network"] = None
    return supersede(out, current)


def git_first_losses(path: str) -> dict[str, float]:
    """Per evaluation key of the record at ``path``: ``training.final_loss`` in the first commit that held the
    evaluation (the network it was made on), from ``git log``; {} outside a git checkout."""
    def git(repo: str, *args) -> str:
        return subprocess.run(["git", "-C", repo, *args], capture_output=True, text=True, check=True).stdout

    try:
        repo = git(os.path.dirname(os.path.abspath(path)), "rev-parse", "--show-toplevel").strip()
        rel = os.path.relpath(os.path.realpath(path), os.path.realpath(repo))
        commits = git(repo, "log", "--format=%H", "--", rel).split()[::-1]
    except (subprocess.CalledProcessError, FileNotFoundError):
        return {}
    first: dict[str, float] = {}
    for commit in commits:
        try:
            snapshot = json.loads(git(repo, "show", f"{commit}:{rel}"))
        except (subprocess.CalledProcessError, json.JSONDecodeError):
            continue
        loss = (snapshot.get("training") or {}).get("final_loss")
        for key in snapshot.get("evaluations", {}):
            first.setdefault(key, loss)
    return first


__all__ = ["RECORD_VERSION", "git_first_losses", "merged", "network", "params_fingerprint", "problems",
           "same_network", "supersede", "upgrade_v1"]
