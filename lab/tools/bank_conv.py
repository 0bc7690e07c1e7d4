"""A teacher bank's trunk, three ways, forward and backward at the reference's shapes (32 members × 128 samples, an
8³ box, 10 channels in, 16 wide): ``torch.func.vmap`` over the members (what ``TeacherBank.forward`` does), a Python
loop over them, and one grouped convolution. Each way three times after a warm-up, twice over, on 2 torch threads.

    python -m lab.tools.bank_conv        # alone on the machine: it times

2026-12-06, the 2-core host, two runs: loop 1.37–1.53 / 1.58–1.78 s, vmap 1.81–2.65 / 2.79–3.11 s, grouped
1.99–2.35 / 2.38–2.79 s a forward and backward (lab/notes/2026-12-06-the-control-reference.md, "Noticed, left alone").
"""

from __future__ import annotations

import time

import torch
from torch.func import functional_call, vmap

MEMBERS, SAMPLES, CHANNELS, HIDDEN, BOX = 32, 128, 10, 16, 8


class Trunk(torch.nn.Module):
    """The context controller's two 3³ convolutions (``ContextConvController``), summed to a scalar a sample."""

    def __init__(self) -> None:
        super().__init__()
        self.a = torch.nn.Conv3d(CHANNELS, HIDDEN, 3, padding=1)
        self.b = torch.nn.Conv3d(HIDDEN, HIDDEN, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.b(torch.relu(self.a(x)))).sum(dim=(1, 2, 3, 4))


def main() -> None:
    torch.set_num_threads(2)
    net = Trunk()
    params = {k: v.detach().unsqueeze(0).repeat(MEMBERS, *[1] * v.dim()).requires_grad_()
              for k, v in net.named_parameters()}
    x = torch.randn(MEMBERS, SAMPLES, CHANNELS, BOX, BOX, BOX)

    def by_vmap() -> None:
        vmap(lambda p, b: functional_call(net, p, (b,)))(params, x).sum().backward()

    def by_loop() -> None:
        outs = [functional_call(net, {k: v[i] for k, v in params.items()}, (x[i],)) for i in range(MEMBERS)]
        torch.stack(outs).sum().backward()

    def grouped() -> None:
        f = torch.nn.functional
        y = x.transpose(0, 1).reshape(SAMPLES, MEMBERS * CHANNELS, BOX, BOX, BOX)
        for name, width in (("a", CHANNELS), ("b", HIDDEN)):
            w = params[f"{name}.weight"].reshape(MEMBERS * HIDDEN, width, 3, 3, 3)
            y = torch.relu(f.conv3d(y, w, params[f"{name}.bias"].reshape(-1), padding=1, groups=MEMBERS))
        y.sum().backward()

    for way in (by_vmap, by_loop, grouped) * 2:
        way()
        t = time.perf_counter()
        for _ in range(3):
            way()
        print(f"{way.__name__}: {(time.perf_counter() - t) / 3:.3f} s a forward and backward")


if __name__ == "__main__":
    main()
