"""PyTorch peer of `g2r-train bench`: the same train step written independently in PyTorch, as the yardstick for
the trainer's throughput (`g2r-train bench --torch PYTHON` runs it and the Rust step alternately; see
docs/performance.md). Same network as train/src/model.rs at `--width` (four down stages w-2w-4w-8w and a 16w
bottleneck, each block two x (conv3x3 -> BatchNorm -> LeakyReLU 0.01) then dropout by depth 0/.1/.2/.3/.3;
2x2 max-pool down; nearest x2 up + conv3x3 + LeakyReLU; skip concatenation; 1x1 head to 3 parameters), an M2
renderer (LeakyReLU 0.01 on the parameters, terms cos i, cos g, 1, times the lit fraction, zero where the surface
faces away from the sun) with normals by central differences over a 130 x 130 DEM with apron, a masked MSE and
an Adam step (lr 1e-4, eps 1e-8).

Prints one JSON line: {"torch": version, "device": ..., "threads": ..., "width": ..., "batch": ...,
"step_ms": ..., "samples_per_s": ...}. Needs torch (and numpy for torch's own import on some builds).
"""
import argparse
import json
import time

import torch
import torch.nn as nn
import torch.nn.functional as F

SLOPE = 0.01
DROPOUT_BY_DEPTH = [0.0, 0.1, 0.2, 0.3, 0.3]


def block(c_in, c_out, p):
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, padding=1), nn.BatchNorm2d(c_out), nn.LeakyReLU(SLOPE),
        nn.Conv2d(c_out, c_out, 3, padding=1), nn.BatchNorm2d(c_out), nn.LeakyReLU(SLOPE),
        nn.Dropout(p),
    )


class UNet(nn.Module):
    def __init__(self, w, out_channels=3, in_channels=1):
        super().__init__()
        widths = [w, 2 * w, 4 * w, 8 * w]
        self.down = nn.ModuleList()
        c = in_channels
        for depth, c_out in enumerate(widths):
            self.down.append(block(c, c_out, DROPOUT_BY_DEPTH[depth]))
            c = c_out
        self.bottleneck = block(c, 16 * w, DROPOUT_BY_DEPTH[4])
        self.up_convs, self.up_blocks = nn.ModuleList(), nn.ModuleList()
        c_up = 16 * w
        for depth in reversed(range(4)):
            self.up_convs.append(nn.Conv2d(c_up, widths[depth], 3, padding=1))
            self.up_blocks.append(block(2 * widths[depth], widths[depth], DROPOUT_BY_DEPTH[depth]))
            c_up = widths[depth]
        self.head = nn.Conv2d(w, out_channels, 1)

    def forward(self, x):
        skips = []
        for down in self.down:
            y = down(x)
            skips.append(y)
            x = F.max_pool2d(y, 2)
        x = self.bottleneck(x)
        for conv, up_block in zip(self.up_convs, self.up_blocks):
            skip = skips.pop()
            up = F.leaky_relu(conv(F.interpolate(x, size=skip.shape[-2:], mode="nearest")), SLOPE)
            x = up_block(torch.cat([up, skip], 1))
        return self.head(x)


def render_m2(params, dem, sun, view, lit, gsd=5.0):
    """M2 rendering from a DEM with a 1-pixel apron: normals by central differences, per-sample sun and view."""
    dz_east = (dem[:, :, 1:-1, 2:] - dem[:, :, 1:-1, :-2]) / (2 * gsd)
    dz_north = (dem[:, :, :-2, 1:-1] - dem[:, :, 2:, 1:-1]) / (2 * gsd)
    normal = F.normalize(torch.cat([-dz_east, -dz_north, torch.ones_like(dz_east)], 1), dim=1)
    cos_i = (normal * sun[:, :, None, None]).sum(1, keepdim=True)
    cos_e = (normal * view[:, :, None, None]).sum(1, keepdim=True)
    cos_g = (sun * view).sum(1)[:, None, None, None].expand_as(cos_i)
    facing = ((cos_i > 0) & (cos_e > 0)).float()
    p = F.leaky_relu(params, SLOPE)
    return lit * facing * (p[:, 0:1] * cos_i + p[:, 1:2] * cos_g + p[:, 2:3])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=int, default=16)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--iters", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(7)
    dev = a.device
    net = UNet(a.width).to(dev)
    net.train()
    opt = torch.optim.Adam(net.parameters(), lr=1e-4, eps=1e-8)
    n = a.batch
    dem = torch.randn(n, 1, 130, 130, device=dev).cumsum(-1).cumsum(-2) * 0.1
    sun = F.normalize(torch.tensor([[0.6, 0.3, 0.5]], device=dev).expand(n, 3), dim=1)
    view = F.normalize(torch.tensor([[0.01, 0.02, 1.0]], device=dev).expand(n, 3), dim=1)
    lit = (torch.rand(n, 1, 128, 128, device=dev) > 0.05).float()
    valid = (torch.rand(n, 1, 128, 128, device=dev) > 0.09).float()
    image = torch.rand(n, 1, 128, 128, device=dev) * 0.05
    centre = dem[:, :, 1:-1, 1:-1]
    x = centre - centre.mean((2, 3), keepdim=True)

    def step():
        opt.zero_grad(set_to_none=True)
        rendered = render_m2(net(x), dem, sun, view, lit)
        loss = (((rendered - image) ** 2) * valid).sum() / valid.sum().clamp(min=1)
        loss.backward()
        opt.step()
        if dev == "cuda":
            torch.cuda.synchronize()

    step()
    start = time.perf_counter()
    for _ in range(a.iters):
        step()
    seconds = (time.perf_counter() - start) / a.iters
    print(json.dumps({
        "torch": torch.__version__, "device": dev, "threads": a.threads, "width": a.width, "batch": n,
        "step_ms": seconds * 1e3, "samples_per_s": n / seconds,
    }))


if __name__ == "__main__":
    main()
