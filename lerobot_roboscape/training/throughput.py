"""Training throughput as the loops log it: samples/s between logging steps, and, with the model's FLOPs per
sample, TFLOP/s and the model FLOPs utilisation against the device's peak."""

import time

import torch

# Dense bf16 peak of the GPUs this project has met (TFLOP/s), by a part of the device's name.
PEAK_BF16_TFLOPS = {"H200": 989.0, "H100": 989.0, "A100": 312.0, "L40S": 362.0, "L4": 121.0, "4090": 165.0}


def peak_flops(device: torch.device, peak_tflops: float | None = None) -> float | None:
    """The device's peak bf16 FLOP/s: `peak_tflops` when given, else the GPU's from PEAK_BF16_TFLOPS; None when
    unknown."""
    if peak_tflops is not None:
        return peak_tflops * 1e12
    if device.type != "cuda":
        return None
    name = torch.cuda.get_device_name(device)
    return next((tflops * 1e12 for key, tflops in PEAK_BF16_TFLOPS.items() if key in name), None)


class Throughput:
    """Samples/s, TFLOP/s and MFU between two logging steps. Reading the clock waits for the device, once per
    logging step, not once per step."""

    def __init__(self, samples_per_step: int, flops_per_sample: float | None, peak: float | None, device):
        self.samples_per_step, self.flops_per_sample, self.peak = samples_per_step, flops_per_sample, peak
        self.device = device
        self.step, self.time = 0, time.perf_counter()

    def _sync(self):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def mark(self, step: int) -> None:
        self._sync()
        self.step, self.time = step, time.perf_counter()

    def read(self, step: int) -> dict[str, float]:
        """The figures since the last mark, which moves here."""
        self._sync()
        seconds = time.perf_counter() - self.time
        samples_per_s = (step - self.step) * self.samples_per_step / max(seconds, 1e-9)
        self.step, self.time = step, time.perf_counter()
        figures = {"samples_per_s": samples_per_s}
        if self.flops_per_sample:
            figures["tflops"] = samples_per_s * self.flops_per_sample / 1e12
            if self.peak:
                figures["mfu"] = samples_per_s * self.flops_per_sample / self.peak
        return figures
