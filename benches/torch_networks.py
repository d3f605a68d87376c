"""PyTorch timings of the network passes that dsgs benchmarks in crates/nets/benches/networks.rs.

Optional and never part of the build or the tests: run by benches/side_by_side.sh when a Python
with PyTorch is available (for example the environment built by ../shared/oracle/setup.sh).
Same shapes as the Rust benches: 256x256 input, fullres (no pooling, no upsampling), float32,
two threads; gradients off except in the decoder forward+backward (input and weight gradients).
Usage: torch_networks.py [THREADS] [PASS ...] (default: 2 threads, every pass).
Prints one line per pass: name, median seconds, GFLOP/s.
"""
import statistics
import sys
import time

import torch
import torch.nn as nn
import torch.nn.functional as F

torch.set_num_threads(int(sys.argv[1]) if len(sys.argv) > 1 else 2)
torch.manual_seed(0)
SIZE = 256


def conv_stack(widths):
    """3x3 reflection-padded convs with ReLU: widths = [c0, c1, ...] consecutive channel counts."""
    layers = []
    for i, o in zip(widths[:-1], widths[1:]):
        layers += [nn.ReflectionPad2d(1), nn.Conv2d(i, o, 3), nn.ReLU()]
    return layers


def encoder(levels):
    # normalised VGG-19 topology, fullres: 1x1 input conv then the conv blocks, no pooling
    plan = {1: [3, 64], 2: [3, 64, 64, 128], 3: [3, 64, 64, 128, 128, 256],
            4: [3, 64, 64, 128, 128, 256, 256, 256, 256, 512]}[levels]
    return nn.Sequential(nn.Conv2d(3, 3, 1), *conv_stack(plan))


def decoder3():
    # WCT relu3_1 inverter, fullres: 256->128, 128->128, 128->64, 64->64, 64->3 (no final ReLU)
    layers = conv_stack([256, 128, 128, 64, 64])
    layers += [nn.ReflectionPad2d(1), nn.Conv2d(64, 3, 3)]
    return nn.Sequential(*layers)


def flops(net, x):
    total, h, w = 0, x.shape[2], x.shape[3]
    for m in net:
        if isinstance(m, nn.Conv2d):
            k = m.kernel_size[0] * m.kernel_size[1]
            total += 2 * m.in_channels * m.out_channels * k * h * w
    return total


def bench(name, net, channels, reps=5):
    x = torch.rand(1, channels, SIZE, SIZE)
    with torch.no_grad():
        net(x)
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            net(x)
            times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    print(f"{name}\t{med:.4f}\t{flops(net, x) / med / 1e9:.1f}")


def bench_forward_backward(name, net, channels, reps=5):
    """Forward with a tape, then the gradients of the input and of every weight for a fixed
    cotangent on the output (as Decoder::forward_with_tape + Decoder::backward in dsgs)."""
    x = torch.rand(1, channels, SIZE, SIZE, requires_grad=True)
    with torch.no_grad():
        cot = torch.rand_like(net(x))

    def step():
        net.zero_grad(set_to_none=True)
        x.grad = None
        net(x).backward(cot)

    step()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    print(f"{name}\t{med:.4f}\t{3 * flops(net, x) / med / 1e9:.1f}")


PASSES = {
    "encoder_relu3_1_fullres_256": lambda n: bench(n, encoder(3), 3),
    "encoder_relu4_1_fullres_256": lambda n: bench(n, encoder(4), 3, reps=3),
    "decoder_relu3_1_fullres_256": lambda n: bench(n, decoder3(), 256),
    "decoder_relu3_1_fullres_forward_backward_256": lambda n: bench_forward_backward(
        n, decoder3(), 256
    ),
}
wanted = sys.argv[2:] or list(PASSES)
unknown = [w for w in wanted if w not in PASSES]
if unknown:
    sys.exit(f"unknown pass {unknown[0]}; the passes are: {', '.join(PASSES)}")
print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads")
print("pass\tseconds\tGFLOP/s")
for name in wanted:
    PASSES[name](name)
