"""Inference runtimes for the CPU hot spots, side by side: prints a markdown table, writes JSON.

Networks: the bundled HardNets (``hardnet``, ``hardnet-full``) on ``--patches`` random 32 x 32
patches, and Local-ScaleNet's feature extractor (one 192 x 192 image). Runtimes:

* PyTorch eager float32 (the weights' layout: HardNet contiguous, scale extractor channels-last),
  bfloat16 autocast, and for HardNet the int8 path of :mod:`localscale.features.quantization`;
* ``torch.compile`` (inductor; the compile time is reported apart, after one warm-up call);
* ONNX Runtime float32 and, for HardNet, its static int8 quantisation
  (``onnxruntime.quantization.quantize_static``, calibrated on the same kind of patches),
  when ``onnxruntime`` and ``onnx`` are installed (they are not dependencies of localscale:
  ``pip install onnxruntime onnx``).

Each entry: median ms of ``--repeat`` calls after a warm-up, and the largest error against
eager float32 (descriptor L2 distance, or feature L2 distance for the extractor).

    OMP_NUM_THREADS=2 python eval/runtime_candidates.py --threads 2 --out results/runtime_candidates.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from localscale.evaluation.report import git_commit
from localscale.features.descriptors import get_descriptor
from localscale.models import LocalScaleNet


def timed(fn, repeat: int) -> float:
    fn()
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts) * 1000)


def onnx_session(module: nn.Module, example: torch.Tensor, path: Path, threads: int, int8_calib=None):
    """An ONNX Runtime session of ``module`` (optionally statically quantised to int8)."""
    import onnxruntime as ort

    torch.onnx.export(
        module,
        example,
        str(path),
        input_names=["x"],
        output_names=["y"],
        dynamic_axes={"x": {0: "batch"}, "y": {0: "batch"}},
        opset_version=17,
        dynamo=False,
    )
    if int8_calib is not None:
        from onnxruntime.quantization import CalibrationDataReader, QuantFormat, quantize_static
        from onnxruntime.quantization.shape_inference import quant_pre_process

        class Reader(CalibrationDataReader):
            def __init__(self):
                self.batches = iter([{"x": int8_calib[i : i + 256].numpy()} for i in range(0, len(int8_calib), 256)])

            def get_next(self):
                return next(self.batches, None)

        pre = path.with_suffix(".pre.onnx")
        quant_pre_process(str(path), str(pre))
        q = path.with_suffix(".int8.onnx")
        quantize_static(str(pre), str(q), Reader(), quant_format=QuantFormat.QDQ, per_channel=True)
        path = q
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__
    )
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--patches", type=int, default=2000)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--no-compile", action="store_true", help="skip torch.compile")
    p.add_argument("--out", default=None, help="JSON file")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    try:
        import onnxruntime  # noqa: F401

        have_ort = True
    except ImportError:
        have_ort = False
        print("note: onnxruntime not installed: its rows are skipped (pip install onnxruntime onnx)", file=sys.stderr)
    rows = []
    x = torch.rand(a.patches, 1, 32, 32)
    calib = torch.rand(1024, 1, 32, 32)
    with tempfile.TemporaryDirectory() as tmp:
        for name in ("hardnet", "hardnet-full"):
            model = get_descriptor(name)
            ref = model.set_precision("fp32").describe(x)
            for prec in ("fp32", "bf16", "int8"):
                model.set_precision(prec)
                ms = timed(lambda: model.describe(x), a.repeat)
                err = float((model.describe(x) - ref).norm(dim=1).max())
                rows.append(
                    {"network": f"{name} {model.widths}", "runtime": f"PyTorch eager {prec}", "ms": ms, "max_err": err}
                )
            model.set_precision("fp32")
            net = model.net.eval()  # per-patch standardisation and unit output included
            if not a.no_compile:
                t = time.perf_counter()
                comp = torch.compile(net)
                with torch.inference_mode():
                    comp(x[:128])
                compile_s = time.perf_counter() - t
                with torch.inference_mode():
                    ms = timed(lambda: [comp(x[i : i + 128]) for i in range(0, len(x), 128)], a.repeat)
                    err = float(
                        (torch.cat([comp(x[i : i + 128]) for i in range(0, len(x), 128)]) - ref).norm(dim=1).max()
                    )
                rows.append(
                    {
                        "network": f"{name} {model.widths}",
                        "runtime": "torch.compile fp32",
                        "ms": ms,
                        "max_err": err,
                        "compile_s": compile_s,
                    }
                )
            if have_ort:
                for label, cal in (("ONNX Runtime fp32", None), ("ONNX Runtime int8 (static, QDQ)", calib)):
                    sess = onnx_session(net, x[:128], Path(tmp) / f"{name}.onnx", a.threads, cal)
                    xn = x.numpy()
                    run = lambda: [sess.run(None, {"x": xn[i : i + 256]})[0] for i in range(0, len(xn), 256)]  # noqa: E731
                    ms = timed(run, a.repeat)
                    err = float((torch.from_numpy(np.concatenate(run())) - ref).norm(dim=1).max())
                    rows.append({"network": f"{name} {model.widths}", "runtime": label, "ms": ms, "max_err": err})

        local = LocalScaleNet.from_pretrained()
        ext = local.extractor.eval()
        img = torch.rand(1, 3, local.config.image_size, local.config.image_size)
        imgc = img.contiguous(memory_format=torch.channels_last)
        plain = LocalScaleNet.from_pretrained().extractor.to(memory_format=torch.contiguous_format).eval()
        with torch.inference_mode():
            ref = ext(imgc)
            rows.append(
                {
                    "network": "Local-ScaleNet extractor",
                    "runtime": "PyTorch eager fp32 (channels-last)",
                    "ms": timed(lambda: ext(imgc), a.repeat),
                    "max_err": 0.0,
                }
            )
            rows.append(
                {
                    "network": "Local-ScaleNet extractor",
                    "runtime": "PyTorch eager fp32 (contiguous)",
                    "ms": timed(lambda: plain(img), a.repeat),
                    "max_err": float((plain(img) - ref).norm(dim=1).max()),
                }
            )

            def bf16():
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    return ext(imgc).float()

            rows.append(
                {
                    "network": "Local-ScaleNet extractor",
                    "runtime": "PyTorch eager bf16",
                    "ms": timed(bf16, a.repeat),
                    "max_err": float((bf16() - ref).norm(dim=1).max()),
                }
            )
            if not a.no_compile:
                t = time.perf_counter()
                comp = torch.compile(ext)
                comp(imgc)
                compile_s = time.perf_counter() - t
                rows.append(
                    {
                        "network": "Local-ScaleNet extractor",
                        "runtime": "torch.compile fp32",
                        "ms": timed(lambda: comp(imgc), a.repeat),
                        "max_err": float((comp(imgc) - ref).norm(dim=1).max()),
                        "compile_s": compile_s,
                    }
                )
        if have_ort:
            sess = onnx_session(plain, img, Path(tmp) / "extractor.onnx", a.threads)
            xn = img.numpy()
            out = torch.from_numpy(sess.run(None, {"x": xn})[0])
            rows.append(
                {
                    "network": "Local-ScaleNet extractor",
                    "runtime": "ONNX Runtime fp32",
                    "ms": timed(lambda: sess.run(None, {"x": xn}), a.repeat),
                    "max_err": float((out - ref).norm(dim=1).max()),
                }
            )

    print(
        f"\n### Inference runtimes (cpu, {a.threads} threads, torch {torch.__version__}; HardNet on {a.patches} "
        f"patches, the extractor on one {local.config.image_size} px image)\n"
    )
    print("| network | runtime | ms (median) | max error vs eager fp32 | compile s |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['network']} | {r['runtime']} | {r['ms']:.1f} | {r['max_err']:.4f} | {r['compile_s']:.0f} |"
            if "compile_s" in r
            else f"| {r['network']} | {r['runtime']} | {r['ms']:.1f} | {r['max_err']:.4f} | |"
        )
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        tmp_out = Path(a.out).with_suffix(".tmp")
        tmp_out.write_text(
            json.dumps(
                {"threads": a.threads, "torch": torch.__version__, "rows": rows, "commit": git_commit()}, indent=1
            )
        )
        tmp_out.replace(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
