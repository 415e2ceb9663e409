"""Per-call latency of a bundled model's nets on each onnxruntime execution provider, by batch size.

Usage: python benchmarks/providers.py [--model egoposevr] [--providers cpu,cuda] [--batches 1,8,32]
                                      [--calls 300]
Prints one markdown table: for each provider, net (fusion, visual encoder) and batch, the median and p99 of
``calls`` timed calls (after 30 untimed ones), in ms, fed numpy arrays exactly as the server feeds them.
It says whether a GPU pays for a net this small: a kernel launch and two copies per call against a CPU call.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import onnxruntime as ort

from egoposevr.model.runtime.loading import LoadedModel, resolve_providers
from egoposevr.model.weights import model_files

WARM_UP_CALLS = 30


def random_feed(session: ort.InferenceSession, batch: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Inputs of the session's shapes, the batch axis (its first, possibly symbolic) set to ``batch``."""
    feed = {}
    for arg in session.get_inputs():
        shape = [batch, *(d if isinstance(d, int) else 1 for d in arg.shape[1:])]
        feed[arg.name] = rng.normal(size=shape).astype(np.float32)
    return feed


def call_ms(session: ort.InferenceSession, feed: dict[str, np.ndarray], calls: int) -> tuple[float, float]:
    """(median, p99) ms of ``calls`` runs after the warm-up."""
    for _ in range(WARM_UP_CALLS):
        session.run(None, feed)
    times = np.empty(calls)
    for i in range(calls):
        started = time.perf_counter()
        session.run(None, feed)
        times[i] = (time.perf_counter() - started) * 1e3
    return float(np.median(times)), float(np.percentile(times, 99))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="egoposevr")
    parser.add_argument("--providers", default="cpu", help="comma-separated; each measured on its own")
    parser.add_argument("--batches", default="1,8,32")
    parser.add_argument("--calls", type=int, default=300)
    args = parser.parse_args()
    batches = [int(b) for b in args.batches.split(",")]
    rng = np.random.default_rng(0)
    print("| provider | net | batch | median (ms) | p99 (ms) | per sample (ms) |")
    print("|---|---|---|---|---|---|")
    for spec in args.providers.split(","):
        model = LoadedModel.load(model_files()[args.model], providers=resolve_providers(spec))
        nets = {"fusion": model.fusion, "visual": model.visual}
        for net_name, session in nets.items():
            if session is None:
                continue
            for batch in batches:
                if batch > 1 and not model.batchable:
                    continue
                median, p99 = call_ms(session, random_feed(session, batch, rng), args.calls)
                print(f"| {session.get_providers()[0]} | {net_name} | {batch} | {median:.3f} | {p99:.3f} | "
                      f"{median / batch:.3f} |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
