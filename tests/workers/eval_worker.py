"""Subprocess worker: the scripted expert on 4 press_button episodes; prints steps, success and output sharding."""

import json, jax
from hipolicy_jax.evaluation import rollout
pf, init = rollout.expert_policy("press_button", 8)
res = rollout.evaluate_stateful(pf, init, "press_button", 4, jax.random.key(3), history_len=1, chunk_len=8)
print(json.dumps({"devices": len(jax.devices()), "steps": [int(x) for x in res.steps], "success": [bool(x) for x in res.success],
                  "sharding": str(res.steps.sharding)}))
