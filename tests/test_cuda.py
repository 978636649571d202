"""On a CUDA machine (skipped elsewhere, CI included): each policy trains through Lightning on the GPU,
its checkpoint loads into a CPU runner (evaluation and rollouts run there), and a runner on the GPU acts as
the CPU one does from the same checkpoint, imagination included.

    python -m pytest tests/test_cuda.py   # on a machine with a GPU
"""

import lightning as L
import numpy as np
import pytest
import torch

from conftest import small_net
from torch.utils.data import DataLoader

from nostra.modality import Modality
from nostra.policies.checkpoint import load_runner
from nostra.policies.modules import policy_module

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
POLICIES = ["nostra", "rssm", "lstm", "diffusion"]
STEPS = 16  # Diffusion Policy's loss denoises a 16-step horizon
NETS = {p: small_net(p) for p in POLICIES[:3]} | {
    "diffusion": dict(embed_dim=16, encoder_hidden=[32], down_dims=[16, 32], step_embed_dim=16)}


@pytest.fixture(autouse=True)
def exact_float32():
    # TF32 would round matmuls and convolutions to 10 mantissa bits: CPU and GPU would then differ by ~1e-3
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = False, False


MODALITIES = [Modality("pos", "lowdim", (2,)), Modality("cam_image", "rgb", (40, 40, 3))]


def episodes(n: int = 8) -> dict:  # random episodes: only devices are compared (nostra.sim needs MuJoCo)
    rng = np.random.default_rng(0)
    return {"obs": {"pos": rng.normal(size=(n, STEPS, 2)).astype(np.float32),
                    "cam_image": rng.integers(0, 256, (n, STEPS, 40, 40, 3), dtype=np.uint8)},
            "actions": rng.uniform(-1, 1, (n, STEPS, 2)).astype(np.float32)}


def loader(data: dict) -> DataLoader:
    collate = lambda idx: {"obs": {k: torch.as_tensor(v[idx]) for k, v in data["obs"].items()},  # noqa: E731
                           "actions": torch.as_tensor(data["actions"][idx])}
    return DataLoader(range(len(data["actions"])), batch_size=4, shuffle=True, collate_fn=collate)


def stats(data: dict) -> dict:  # the store's statistics (nostra.data.stats) without the store's imports
    arrays = {k: v for k, v in data["obs"].items() if v.dtype != np.uint8} | {"actions": data["actions"]}
    return {k: {"mean": v.reshape(-1, v.shape[-1]).mean(0), "std": v.reshape(-1, v.shape[-1]).std(0),
                "min": v.reshape(-1, v.shape[-1]).min(0), "max": v.reshape(-1, v.shape[-1]).max(0)}
            for k, v in arrays.items()}


class OnDevice(L.Callback):
    """Where the parameters and the batches are while Lightning trains."""
    def __init__(self):
        self.seen = set()

    def on_train_batch_start(self, trainer, module, batch, batch_idx):
        self.seen |= {p.device.type for p in module.parameters()} | {batch["actions"].device.type}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root, data, out = tmp_path_factory.mktemp("cuda"), episodes(), {}
    for policy in POLICIES:
        torch.manual_seed(0)
        module = policy_module(policy)([m.to_dict() for m in MODALITIES], 2,
                                       net=NETS[policy], optim={"lr": 1e-3})
        module.set_normalization(stats(data))
        before = {k: v.clone() for k, v in module.state_dict().items()}
        where = OnDevice()
        trainer = L.Trainer(max_steps=10, accelerator="gpu", devices=1, logger=False, enable_checkpointing=False,
                            enable_progress_bar=False, enable_model_summary=False, callbacks=[where])
        trainer.fit(module, loader(data))
        path = root / f"{policy}.ckpt"
        trainer.save_checkpoint(path)
        out[policy] = dict(path=path, where=where.seen, before=before, after=module.state_dict(),
                           loss=float(trainer.callback_metrics["train/loss"]))
    return out, data


@pytest.mark.parametrize("policy", POLICIES)
def test_lightning_trains_each_policy_on_the_gpu(trained, policy):
    run = trained[0][policy]
    assert run["where"] == {"cuda"}  # parameters and batches, every step
    assert np.isfinite(run["loss"])
    changed = [k for k, v in run["before"].items() if v.is_floating_point() and
               not torch.equal(v, run["after"][k].cpu()) and "normalizer" not in k]
    assert changed, "no weight moved in 10 optimiser steps"


@pytest.mark.parametrize("policy", POLICIES)
def test_a_gpu_checkpoint_runs_on_the_cpu_and_the_gpu_alike(trained, policy):
    runs, data = trained
    obs = [{k: v[0, t] for k, v in data["obs"].items()} for t in range(STEPS)]
    cpu = load_runner(runs[policy]["path"])
    gpu = load_runner(runs[policy]["path"], device="cuda")
    assert next(cpu.net.parameters()).device.type == "cpu" and next(gpu.net.parameters()).device.type == "cuda"
    a_cpu = np.stack([cpu.step(o)[0] for o in obs])
    a_gpu = np.stack([gpu.step(o)[0] for o in obs])
    assert np.isfinite(a_cpu).all() and a_cpu.shape == (STEPS, 2)
    if policy != "diffusion":  # diffusion samples its noise from each device's own generator
        np.testing.assert_allclose(a_gpu, a_cpu, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("policy", ["nostra", "rssm"])
def test_imagination_on_the_gpu_matches_the_cpu(trained, policy):
    runs, data = trained
    obs = [{k: v[0, t] for k, v in data["obs"].items()} for t in range(STEPS)]
    imagine = lambda t: ["cam_image"] if 4 <= t < 9 else None  # noqa: E731  a window of imagined frames
    steps = {}
    for device in ("cpu", "cuda"):
        r = load_runner(runs[policy]["path"], device=device)
        steps[device] = [r.step(o, imagine=imagine(t)) for t, o in enumerate(obs)]
    np.testing.assert_allclose(np.stack([a for a, _ in steps["cuda"]]), np.stack([a for a, _ in steps["cpu"]]),
                               rtol=1e-4, atol=1e-4)
    assert [i["imagined"]["cam_image"] for _, i in steps["cuda"]] == [4 <= t < 9 for t in range(STEPS)]
    if policy == "nostra":  # AdaMLI's input: the per-modality KL, read back from the GPU
        kl = lambda d: np.array([list(i["kl"].values()) for _, i in steps[d]])  # noqa: E731
        np.testing.assert_allclose(kl("cuda"), kl("cpu"), rtol=1e-3, atol=1e-4)
