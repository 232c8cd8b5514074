"""``SpeedupConfig``: DemoSpeedup's settings, each a named field with the default of the authors' public code
(``lingxiao-guo/DemoSpeedup``; the paper, arXiv 2506.05064, describes the same pipeline).

Where the defaults come from:

- ``num_samples`` = 10: the authors' labelling pass (``label_entropy`` in ``aloha/act/imitate_episodes.py``) draws 10
  samples per predicted chunk (``all_time_samples`` of shape ``(T, T + chunk, 10, dim)``). That pass also pools the
  samples of every earlier chunk that predicted the same frame (temporal ensembling); here the N samples are the N
  chunks drawn at the frame itself, the estimator the paper states (the first action of N sampled chunks).
- ``bandwidth`` = 0.002 and ``density_eps`` = 1e-8: ``KDE.kde_entropy`` in ``act/detr/models/entropy_utils.py``
  (bandwidth hard-coded, "0.002 for insertion, 0.001 for transfer"; ``log(density + 1e-8)``), applied to the
  network's normalised actions, so here to the proxy's normalised actions (``Normalizer.normalize('action')``).
- ``bandwidth_ladder`` = () and ``max_saturated`` = 0.5: not upstream's. Upstream tuned the bandwidth by hand per task
  ("0.002 for insertion, 0.001 for transfer"). A bandwidth far below the spread of a proxy's samples puts every frame at
  the estimator's ceiling log N, leaving the segmentation nothing to read. With a ladder, the stage measures the
  entropies under ``bandwidth`` and each larger candidate, and takes the first under which at most ``max_saturated``
  of the frames sit at the ceiling (``entropy.choose_bandwidth``); none fits: the last. This is a rule fixed before
  seeing any policy's success, in place of upstream's tuning by hand.
- ``casual_prefix`` = 50 frames: ``hdbscan_with_custom_merge`` marks the first 50 frames as noise, which become casual
  (label 1). Upstream records at 50 Hz, so this is its first second; our MJX tasks run at 10 Hz, where 50 frames is
  5 s (most of a press_button demo): pass ``casual_prefix`` 10 for the same duration.
- ``min_segment`` = 5 and ``precise_z`` = 0: upstream clusters each demo's (z-scored time, z-scored entropy) points
  with HDBSCAN(min_cluster_size=5) and labels a cluster precise when its z-scored entropy is below the demo's mean
  (sign 0), noise casual. Neither ``hdbscan`` nor scikit-learn is a dependency here, so ``retime.label_frames`` keeps
  the rule's three parts without the clustering: the per-demo z-score, a running median over ``min_segment`` frames
  (a dip shorter than a cluster is noise), precise below ``precise_z`` in runs of at least ``min_segment`` frames.
- ``precise_rate`` = 2 and ``casual_rate`` = 4: ``process_action_label`` in the authors' ``act_utils.py``
  (``low_v = 2``, ``high_v = 4``): a precise frame advances 2 frames; a casual frame advances 4 when the next 4 are
  all casual, else jumps to the next precise frame.
"""

from __future__ import annotations

import dataclasses


def _check(ok: bool, field: str, expected: str, got) -> None:
    if not ok:
        raise ValueError(f"speedup.{field}: {expected}, got {got!r}")


@dataclasses.dataclass(frozen=True)
class SpeedupConfig:
    """DemoSpeedup's estimator, segmentation and rates (module docstring: where each default comes from)."""

    num_samples: int = 10  # N action chunks drawn by the proxy at every demo frame (>= 2 for a density)
    bandwidth: float = 0.002  # Gaussian kernel bandwidth (std), in the proxy's normalised action units
    density_eps: float = 1e-8  # added to the kernel density before its log
    casual_prefix: int = 50  # the first frames of every demo are casual (upstream: 50 frames at 50 Hz, i.e. 1 s)
    min_segment: int = 5  # frames: running-median window and the shortest precise segment (HDBSCAN min_cluster_size)
    precise_z: float = 0.0  # a frame is precise when its demo-z-scored, median-filtered entropy is below this
    bandwidth_ladder: tuple[float, ...] = ()  # larger bandwidths to try when too many frames saturate (docstring)
    max_saturated: float = 0.5  # the ladder's rule: the largest fraction of frames at the ceiling log N it accepts
    precise_rate: int = 2  # frames a precise frame advances (upstream low_v)
    casual_rate: int = 4  # frames a casual frame advances when the next ones are all casual (upstream high_v)

    def __post_init__(self):
        _check(isinstance(self.num_samples, int) and self.num_samples >= 2, "num_samples",
               "must be an integer >= 2 (a kernel density needs two samples)", self.num_samples)
        _check(self.bandwidth > 0, "bandwidth", "must be > 0", self.bandwidth)
        _check(all(b > self.bandwidth for b in self.bandwidth_ladder)
               and list(self.bandwidth_ladder) == sorted(set(self.bandwidth_ladder)), "bandwidth_ladder",
               f"must be increasing bandwidths, each > bandwidth={self.bandwidth}", self.bandwidth_ladder)
        _check(0.0 <= self.max_saturated <= 1.0, "max_saturated", "must be a fraction in [0, 1]", self.max_saturated)
        _check(self.density_eps >= 0, "density_eps", "must be >= 0", self.density_eps)
        _check(isinstance(self.casual_prefix, int) and self.casual_prefix >= 0, "casual_prefix",
               "must be an integer >= 0 (frames)", self.casual_prefix)
        _check(isinstance(self.min_segment, int) and self.min_segment >= 1, "min_segment",
               "must be an integer >= 1 (frames)", self.min_segment)
        _check(isinstance(self.precise_rate, int) and self.precise_rate >= 1, "precise_rate",
               "must be an integer >= 1 (frames per kept frame)", self.precise_rate)
        _check(isinstance(self.casual_rate, int) and self.casual_rate >= self.precise_rate, "casual_rate",
               f"must be an integer >= precise_rate={self.precise_rate} (casual parts go at least as fast)",
               self.casual_rate)

    def bandwidths(self) -> tuple[float, ...]:
        """The candidate bandwidths in the order the ladder rule tries them: ``bandwidth``, then the ladder."""
        return (float(self.bandwidth), *(float(b) for b in self.bandwidth_ladder))

    def rate(self, label: int) -> int:
        """The declared rate of a segment label (``retime.PRECISE`` or ``retime.CASUAL``)."""
        return self.precise_rate if label == 0 else self.casual_rate
