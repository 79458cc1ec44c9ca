"""The README's Python example runs as written and its PF estimate is near the KF's."""

import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README.md has no python example"
    namespace: dict = {}
    exec(compile("\n".join(blocks), str(README), "exec"), namespace)  # noqa: S102
    pf, kf = namespace["pf"], namespace["kf"]
    # 32 runs × 100 steps, N = 1000: the PF log-likelihood is close to the exact value
    assert torch.allclose(pf.log_likelihood.mean(), kf.log_likelihood.mean(), rtol=0.01)
    assert namespace["kf_lossy"].means.shape == (32, 100, 2)
    out = namespace["out"]  # the estimator-contract example
    assert out.means.shape == (32, 100, 2) and out.attack.shape == (32, 100, 1)
    assert out.detection.alarms.dtype == torch.bool
    # the loop example: the open loop is the whole-sequence filter, the replay is exact
    torch.testing.assert_close(namespace["whole"].means, kf.means)
    loop = namespace["replayed"].trajectories
    recorded = 39 + torch.arange(41) % 20  # steps 40..59, cycled from step 60 on
    torch.testing.assert_close(loop.y_recv[:, 59:], loop.y_true[:, recorded], rtol=0, atol=0)
    torch.testing.assert_close(loop.y_recv[:, :59], loop.y_true[:, :59], rtol=0, atol=0)
    # the input-loss example: acknowledged and unattacked, the estimator knows what was
    # applied; the actuators held their input wherever a packet was lost
    lossy = namespace["lossy"].trajectories
    applied = lossy.info["inputs_applied"]
    torch.testing.assert_close(lossy.us, applied, rtol=0, atol=0)
    lost = ~namespace["arrived"][:, 1:]
    assert bool(lost.any()) and torch.equal(applied[:, 1:][lost], applied[:, :-1][lost])
    # the online example: one run's last PF estimate within 3 posterior sd of the KF's
    online = namespace["online_out"]
    sd = kf.covs[0, -1].diagonal().sqrt()
    assert online.mean.shape == (2,) and bool(
        ((online.mean - kf.means[0, -1]).abs() < 3 * sd).all()
    )
