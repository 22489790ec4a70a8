"""Network benchmark (DESIGN §8/§10): parameters, training throughput, onnxruntime fp32 vs int8 latency.

For each architecture and input size: parameter count; training samples/s (AdamW + L1, batch 8, on
`threads` torch threads, after one warm-up step); fp32 ONNX export and static int8 QDQ quantization
calibrated on synthetic inputs; single-thread onnxruntime latency of fp32 and int8 measured
alternately in one loop (so machine load hits both equally). Untrained weights: latency does not
depend on them. Inputs are the synthetic generator's images (structured, not physics).
"""
from __future__ import annotations

import logging
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def _inputs(size: int, n: int, seed: int = 0) -> np.ndarray:
    from .model.data import synthetic_sample

    rng = np.random.default_rng(seed)
    return np.stack([synthetic_sample(rng, size)[0] for _ in range(n)]).astype(np.float32) / 255.0


def train_throughput(model, size: int, threads: int, steps: int, batch: int = 8) -> float:
    import torch

    torch.set_num_threads(threads)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    x, y = torch.rand(batch, 6, size, size), torch.rand(batch, 15, size, size)
    model.train()
    for i in range(steps + 1):
        if i == 1:
            t0 = time.perf_counter()
        loss = torch.nn.functional.l1_loss(model(x), y)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return steps * batch / (time.perf_counter() - t0)


def run_bench(sizes=(96, 128), archs=("hiera_qup", "unet", "vit"), threads: int = 2, steps: int = 6,
              latency_runs: int = 60) -> dict:
    from .export import ExportConfig, export_onnx, latency_ms, quantize_int8
    from .model import build_model
    from .model.layers import count_params

    res = {"machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                       "load_avg_start": list(os.getloadavg())},
           "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "models": []}
    cfg = ExportConfig(latency_runs=latency_runs)
    for size in sizes:
        x = _inputs(size, 24)
        for arch in archs:
            model = build_model(arch, size)
            row = {"arch": arch, "size": size, "params": count_params(model)}
            row["train_samples_per_s"] = train_throughput(model, size, threads, steps)
            with tempfile.TemporaryDirectory() as tmp:
                fp32, int8 = Path(tmp) / "fp32.onnx", Path(tmp) / "int8.onnx"
                export_onnx(model, fp32, size)
                quantize_int8(fp32, int8, x[:16], cfg)
                lat = latency_ms({"fp32": fp32, "int8": int8}, x[16:], cfg)
            row["latency_ms"] = lat
            row["int8_speedup"] = lat["fp32"]["median"] / lat["int8"]["median"]
            log.info("%s %d: %d params, %.1f train samples/s, fp32 %.2f ms, int8 %.2f ms", arch, size,
                     row["params"], row["train_samples_per_s"], lat["fp32"]["median"], lat["int8"]["median"])
            res["models"].append(row)
    res["machine"]["load_avg_end"] = list(os.getloadavg())
    return res
