"""The PyTorch peer of the throughput comparison: Diffusion Policy's 1D U-Net in PyTorch, timed on this machine.

    python -m benchmarks.studies.pytorch_peer            # needs torch (not a dependency of this package)
    python -m benchmarks.studies.pytorch_peer --shapes dp-lowdim --ns 1 100 --threads 2

The network is Diffusion Policy's ``ConditionalUnet1D`` at paper size (down dims 256/512/1024, kernel 5, 8 groups,
a 256-dim step embedding, FiLM scale and bias), written here in plain PyTorch so the comparison with
``benchmarks.sampling --shapes`` / ``benchmarks.train_step --shapes`` runs on the same machine:

- ``dp-lowdim``: one stride, A = 2, T = 16, the raw observation window (2 x 20) as the global condition:
  65,783,298 parameters, as Diffusion Policy's low-dim U-Net;
- ``hipolicy-nofusion``: strides 1/2/3, L_c = 8 -> T = 24, A = 14, one 40-dim condition per segment
  (per-segment FiLM, the same U-Net body);
- ``hipolicy``: the same plus HiPolicy's CLS-token fusion in both residual blocks of the first level.

Sampling is DDPM with 100 steps (squared-cosine betas, epsilon prediction, clipped x0), N samples of one
observation in one batch, under ``torch.inference_mode``. The train step is Diffusion Policy's: noise, random
steps, MSE, backward, AdamW (lr 1e-4, weight decay 1e-6) and the per-parameter EMA update, at ``--batch``.
Times are medians after a warm-up call, with ``--threads`` intra-op threads. Writes
``benchmarks/studies/results/pytorch_peer_cpu.json`` (standard library JSON: this script does not import JAX).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time

import torch
from torch import nn

from benchmarks.machine import machine_info
import torch.nn.functional as F

def torch_peaks(n: int = 2048, mbytes: int = 256, repeats: int = 5) -> dict:
    """The machine peaks as ``benchmarks.common.machine_peaks`` measures them, in PyTorch (this script does not import
    JAX): the best GFLOP/s of an n x n float32 matmul and GB/s of summing an ``mbytes`` MB float32 array."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    big = torch.ones(mbytes * 2**20 // 4)

    def best(fn):
        fn()
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return min(times), statistics.median(times)

    mm, mm_med = best(lambda: torch.mm(a, b))
    bw, bw_med = best(lambda: big.sum())
    return {"matmul_f32_gflops": 2.0 * n**3 / mm / 1e9, "matmul_n": n,
            "matmul_f32_median_gflops": 2.0 * n**3 / mm_med / 1e9,
            "bandwidth_gbs": big.numel() * 4 / bw / 1e9, "bandwidth_mbytes": mbytes,
            "bandwidth_median_gbs": big.numel() * 4 / bw_med / 1e9}


SHAPES = {  # name -> (strides / segments M, chunk len per segment, action dim, condition dim per segment, fusion)
    "dp-lowdim": (1, 16, 2, 40, False),
    "hipolicy-nofusion": (3, 8, 14, 40, False),
    "hipolicy": (3, 8, 14, 40, True),
}
DOWN_DIMS, KERNEL, GROUPS, STEP_DIM, HEADS = (256, 512, 1024), 5, 8, 256, 8


class Conv1dBlock(nn.Module):
    def __init__(self, c_in, c_out, k):
        super().__init__()
        self.conv, self.norm = nn.Conv1d(c_in, c_out, k, padding=k // 2), nn.GroupNorm(GROUPS, c_out)

    def forward(self, x):
        return F.mish(self.norm(self.conv(x)))


class Fusion(nn.Module):
    """CLS-token self-attention over the M segment tokens of size L_c * C of each sample."""

    def __init__(self, segments, seg_len, c):
        super().__init__()
        self.m, d = segments, seg_len * c
        self.cls = nn.Parameter(torch.randn(1, 1, d))
        self.attn = nn.MultiheadAttention(d, HEADS, batch_first=True)

    def forward(self, x):  # (B, C, M * L) -> (B, C, M * L): the CLS output tiled over the segments
        b, c, t = x.shape
        tok = x.reshape(b, c, self.m, t // self.m).permute(0, 2, 3, 1).reshape(b, self.m, -1)
        tok = torch.cat([self.cls.expand(b, -1, -1), tok], 1)
        glob = self.attn(tok, tok, tok, need_weights=False)[0][:, 0].reshape(b, t // self.m, c).permute(0, 2, 1)
        return glob.repeat(1, 1, self.m)


class ResBlock(nn.Module):
    def __init__(self, c_in, c_out, cond_dim, segments, fusion_len=0):
        super().__init__()
        self.c, self.m = c_out, segments
        self.fusion = Fusion(segments, fusion_len, c_in) if fusion_len else None
        wide = 2 if fusion_len else 1
        self.block0 = Conv1dBlock(wide * c_in, wide * c_out, KERNEL)
        self.block1 = Conv1dBlock(wide * c_out, c_out, KERNEL) if fusion_len else Conv1dBlock(c_out, c_out, KERNEL)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * c_out))
        self.residual = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x, cond):  # x (B, C, T), cond (B, K, cond_dim) with K | T
        embed = self.film(cond)  # (B, K, 2C)
        h_in = torch.cat([x, self.fusion(x)], 1) if self.fusion is not None else x
        h = self.block0(h_in)
        local = h[:, :self.c]
        b, c, t = local.shape
        k = embed.shape[1]
        scale = embed[..., :c].permute(0, 2, 1).repeat_interleave(t // k, -1)
        bias = embed[..., c:].permute(0, 2, 1).repeat_interleave(t // k, -1)
        local = local * scale + bias
        h = torch.cat([local, h[:, self.c:]], 1) if self.fusion is not None else local
        return self.block1(h) + self.residual(x)


class ConditionalUnet1D(nn.Module):
    def __init__(self, action_dim, cond_dim, segments, seg_len, fusion):
        super().__init__()
        d = STEP_DIM
        self.step = nn.Sequential(nn.Linear(d, 4 * d), nn.Mish(), nn.Linear(4 * d, d))
        cdim = d + cond_dim
        dims = (action_dim,) + DOWN_DIMS
        pairs = list(zip(dims[:-1], dims[1:]))
        self.down = nn.ModuleList()
        for i, (a, b) in enumerate(pairs):
            fl = seg_len if (fusion and i == 0) else 0
            self.down.append(nn.ModuleList([ResBlock(a, b, cdim, segments, fl), ResBlock(b, b, cdim, segments, fl),
                                            nn.Conv1d(b, b, 3, 2, 1) if i < len(pairs) - 1 else nn.Identity()]))
        self.mid = nn.ModuleList([ResBlock(DOWN_DIMS[-1], DOWN_DIMS[-1], cdim, segments) for _ in range(2)])
        self.up = nn.ModuleList()
        for a, b in reversed(pairs[1:]):
            self.up.append(nn.ModuleList([ResBlock(2 * b, a, cdim, segments), ResBlock(a, a, cdim, segments),
                                          nn.ConvTranspose1d(a, a, 4, 2, 1)]))
        self.final = nn.Sequential(Conv1dBlock(DOWN_DIMS[0], DOWN_DIMS[0], KERNEL), nn.Conv1d(DOWN_DIMS[0], action_dim, 1))

    def forward(self, x, t, cond):  # x (B, T, A), t (B,), cond (B, K, Dc) -> (B, T, A)
        half = STEP_DIM // 2
        freqs = torch.exp(torch.arange(half, dtype=torch.float32) * -(math.log(10000.0) / (half - 1)))
        arg = t.float()[:, None] * freqs
        step = self.step(torch.cat([arg.sin(), arg.cos()], -1))
        c = torch.cat([step[:, None].expand(-1, cond.shape[1], -1), cond], -1)
        h = x.transpose(1, 2)
        skips = []
        for r0, r1, down in self.down:
            h = r1(r0(h, c), c)
            skips.append(h)
            h = down(h)
        for r in self.mid:
            h = r(h, c)
        for r0, r1, up in self.up:
            h = up(r1(r0(torch.cat([h, skips.pop()], 1), c), c))
        return self.final(h).transpose(1, 2)


def betas_squaredcos(n=100, max_beta=0.999):
    f = lambda t: math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
    return torch.tensor([min(1 - f((i + 1) / n) / f(i / n), max_beta) for i in range(n)])


def ddpm_sample(net, cond, n, horizon, action_dim, steps=100, gen=None):
    betas = betas_squaredcos(steps)
    alphas = 1.0 - betas
    abar = torch.cumprod(alphas, 0)
    x = torch.randn(n, horizon, action_dim, generator=gen)
    cond = cond.expand(n, -1, -1)
    for t in reversed(range(steps)):
        eps = net(x, torch.full((n,), t), cond)
        ab, ab_prev = abar[t], abar[t - 1] if t > 0 else torch.tensor(1.0)
        x0 = ((x - (1 - ab).sqrt() * eps) / ab.sqrt()).clamp(-1, 1)
        mean = (ab_prev.sqrt() * betas[t] / (1 - ab)) * x0 + (alphas[t].sqrt() * (1 - ab_prev) / (1 - ab)) * x
        if t > 0:
            var = (1 - ab_prev) / (1 - ab) * betas[t]
            mean = mean + var.clamp(min=1e-20).sqrt() * torch.randn(x.shape, generator=gen)
        x = mean
    return x


def timed(fn, repeats):
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m benchmarks.studies.pytorch_peer", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--shapes", nargs="+", default=list(SHAPES), choices=list(SHAPES))
    p.add_argument("--ns", nargs="+", type=int, default=[1, 100])
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--skip-train", action="store_true")
    p.add_argument("--out-dir", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results"))
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    rows = []
    for shape in args.shapes:
        m, lc, a, dc, fusion = SHAPES[shape]
        net = ConditionalUnet1D(a, dc, m, lc, fusion)
        params = sum(q.numel() for q in net.parameters())
        cond = torch.rand(1, m, dc) * 2 - 1
        print(f"[{shape}] {params:,} parameters", flush=True)
        net.eval()
        for n in args.ns:
            with torch.inference_mode():
                med, times = timed(lambda: ddpm_sample(net, cond, n, m * lc, a), args.repeats)
            rows.append({"shape": shape, "params": params, "workload": "sample", "n": n, "steps": 100,
                         "median_s": med, "times_s": times})
            print(f"  sample N={n}, DDPM 100: {med:.2f} s", flush=True)
        if args.skip_train:
            continue
        net.train()
        opt = torch.optim.AdamW(net.parameters(), lr=1e-4, betas=(0.95, 0.999), weight_decay=1e-6)
        ema = [q.detach().clone() for q in net.parameters()]
        x = torch.rand(args.batch, m * lc, a) * 2 - 1
        c = torch.rand(args.batch, m, dc) * 2 - 1

        def step():
            noise = torch.randn_like(x)
            t = torch.randint(0, 100, (args.batch,))
            loss = F.mse_loss(net(x + noise, t, c), noise)  # the schedule's mixing is element-wise and cheap
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            with torch.no_grad():
                for e, q in zip(ema, net.parameters()):  # Diffusion Policy's EMAModel: one update per parameter
                    e.mul_(0.999).add_(q, alpha=0.001)

        med, times = timed(step, max(args.repeats, 5))
        rows.append({"shape": shape, "params": params, "workload": "train", "batch": args.batch, "median_s": med,
                     "times_s": times})
        print(f"  train step, batch {args.batch}: {med:.3f} s", flush=True)
    os.makedirs(args.out_dir, exist_ok=True)
    path = os.path.join(args.out_dir, "pytorch_peer_cpu.json")
    payload = {"benchmark": "pytorch_peer", "torch_version": torch.__version__, "threads": args.threads,
               "cpu_count": os.cpu_count(), "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
               "machine": machine_info(torch_peaks),
               "command": "python -m benchmarks.studies.pytorch_peer "
                          + " ".join(sys.argv[1:] if argv is None else argv),
               "rows": rows}
    with open(path, "w") as f:
        json.dump(payload, f, indent=1)
        f.write("\n")
    print(f"wrote {path}")
    return payload


if __name__ == "__main__":
    main()
