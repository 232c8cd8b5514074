"""DemoSpeedup (Guo et al., arXiv 2506.05064, CoRL 2025) as a data stage: a demo buffer and a trained proxy policy in,
an accelerated demo buffer in the same zarr layout out.

The method: a proxy generative policy trained on the normal-speed demos samples N action chunks at every demo frame;
the entropy of the first action is estimated with a Gaussian kernel density over the N samples; each demo is split by
entropy into precise (low-entropy) and casual (high-entropy) segments, and downsampled at a rate per segment (casual
parts faster). The policy is then retrained on the accelerated demos.

Modules, in the order the stage runs them (each states its shapes at its boundary):

- ``config``: ``SpeedupConfig``, the estimator's, the segmentation's and the rates' fields with the paper's defaults
  (where each default comes from is in its docstring);
- ``entropy``: the kernel-density entropy estimator (pure) and the proxy's per-frame entropies
  (``sampling.make_sampler`` over fixed-size batches of every frame's observation window);
- ``retime``: pure numpy: per-frame labels from entropies, the frames each episode keeps, the episodes re-derived on the
  accelerated timeline (absolute targets: the kept frames'; delta dimensions: the sum of the deltas a kept frame
  replaces), the accelerated ``ReplayBuffer``;
- ``stage``: reading the buffer, refusing a proxy of another task / action size / observations in one line, writing the
  accelerated buffer with the source's root attributes and a ``speedup`` record;
- ``plot``: one demo's entropy over time with its segments and rates shaded.

It uses a trained run (``runs.store``), so it sits beside ``runs``; ``experiments.speedup`` is its command line.
Its place in the flow: data (a demo buffer) -> **speedup** (with a proxy policy that went through the whole flow)
-> data again (the accelerated buffer, on which the policy is retrained).

Public names re-exported here: ``SpeedupConfig``; ``kde_entropy``, ``frame_entropies``, ``ladder_entropies``, ``choose_bandwidth``,
``saturated_fraction``;
``label_frames``, ``segments``, ``keep_indices``, ``retime_episode``, ``accelerate``, ``PRECISE``, ``CASUAL``;
``speedup_demos``, ``check_proxy_fits``, ``buffer_task``, ``SPEEDUP_ATTR``.
"""

from hipolicy_jax.speedup.config import SpeedupConfig
from hipolicy_jax.speedup.entropy import (choose_bandwidth, frame_entropies, kde_entropy, ladder_entropies,
                                          saturated_fraction)
from hipolicy_jax.speedup.retime import (CASUAL, PRECISE, accelerate, keep_indices, label_frames, retime_episode,
                                         segments)
from hipolicy_jax.speedup.stage import SPEEDUP_ATTR, buffer_task, check_proxy_fits, speedup_demos

__all__ = ["CASUAL", "PRECISE", "SPEEDUP_ATTR", "SpeedupConfig", "accelerate", "buffer_task", "check_proxy_fits",
           "choose_bandwidth", "frame_entropies", "kde_entropy", "keep_indices", "label_frames", "ladder_entropies",
           "retime_episode", "saturated_fraction", "segments", "speedup_demos"]
