#!/usr/bin/env python3
"""Numpy ports of fedvla's Rust image path, compared with LeRobot fixtures (no Rust build needed).

usage (inside the lerobot-check chroot): python3 check_image_path.py FIXTURE_DIR...

For every camera of each fixture it reports:
  * `prepare_image` (shared/policy/src/batch.rs) vs LeRobot's `prepared.images.<cam>`;
  * the exact PyTorch CPU form (1 thread, C=3: FMA-contracted source index and 4-weight sum) vs the same,
    which is bitwise on this host (AVX512 torch 2.14.1+debian);
  * SmolVLM position ids (shared/policy/src/vision.rs `position_ids`) vs `vision.<cam>.position_ids`;
  * the data crate's u8 resize (shared/data/src/image.rs `resized_with_pad`) vs LeRobot's float path;
  * fedvla's camera order (`SmolVlaConfig::camera_keys`, alphabetical because serde_json::Map is a
    BTreeMap without the `preserve_order` feature) vs LeRobot's (config.json input_features order), and
    what the image part of `fm.prefix_embs` looks like in each order.
"""
import sys, json, numpy as np
from safetensors.numpy import load_file
f32 = np.float32

def resize_bilinear(src, c, h, w, oh, ow):           # policy/src/batch.rs:61
    def coords(out, inp):
        scale = f32(inp) / f32(out)
        r = []
        for o in range(out):
            real = max(f32((f32(o) + f32(0.5)) * scale - f32(0.5)), f32(0.0))
            i0 = min(int(np.floor(real)), inp - 1); i1 = min(i0 + 1, inp - 1)
            r.append((i0, i1, f32(real - f32(i0))))
        return r
    ys, xs = coords(oh, h), coords(ow, w)
    out = np.zeros((c, oh, ow), f32)
    for ch in range(c):
        p = src[ch]
        for yi, (y0, y1, ly) in enumerate(ys):
            for xi, (x0, x1, lx) in enumerate(xs):
                top = f32(f32(f32(1) - lx) * p[y0, x0]) + f32(lx * p[y0, x1])
                bot = f32(f32(f32(1) - lx) * p[y1, x0]) + f32(lx * p[y1, x1])
                out[ch, yi, xi] = f32(f32(f32(1) - ly) * f32(top)) + f32(ly * f32(bot))
    return out

def prepare_image(img, tw, th):                        # policy/src/batch.rs:90
    b, c, h, w = img.shape
    out = np.zeros((b, c, th, tw), f32)
    for n in range(b):
        if h == th and w == tw:
            out[n] = img[n] * f32(2) - f32(1); continue
        ratio = max(w / tw, h / th)
        rh, rw = int(h / ratio), int(w / ratio)
        rs = resize_bilinear(img[n], c, h, w, rh, rw)
        pt, pl = th - rh, tw - rw
        full = np.zeros((c, th, tw), f32); full[:, pt:, pl:] = rs
        out[n] = full * f32(2) - f32(1)
    return out

def position_ids(image_size, patch, rows, cols):     # policy/src/vision.rs:88
    per = image_size // patch; step = f32(1) / f32(per)
    bnd = [f32(k) * step for k in range(1, per)]
    bucket = lambda n: [sum(1 for bb in bnd if bb <= f32(i) / f32(n)) for i in range(n)]
    rb, cb = bucket(rows), bucket(cols)
    return [r * per + cc for r in rb for cc in cb]

for d in sys.argv[1:]:
    cfg = json.load(open(f"{d}/config.json")); vc = json.load(open(f"{d}/vlm/config.json"))["vision_config"]
    inp, out = load_file(f"{d}/inputs.safetensors"), load_file(f"{d}/outputs.safetensors")
    tw, th = cfg["resize_imgs_with_padding"]
    lerobot_order = [k for k, v in cfg["input_features"].items() if v["type"] == "VISUAL"]
    rust_order = sorted(lerobot_order)   # serde_json::Map without preserve_order = BTreeMap
    print(f"== {d}: lerobot camera order {lerobot_order}; fedvla camera_keys() {rust_order}"
          + ("  <-- DIFFERENT" if rust_order != lerobot_order else ""))
    for k in lerobot_order:
        ref = out[f"prepared.images.{k}"]; mine = prepare_image(inp[k], tw, th)
        dif = np.abs(ref.astype(np.float64) - mine).max()
        # padding check
        h, w = inp[k].shape[2:]
        print(f"  {k} {h}x{w} -> {th}x{tw}: prepare_image max|diff| {dif:.3g}"
              f" (bitwise {np.array_equal(ref, mine)})")
        ids = out[f"vision.{k}.position_ids"]
        p = vc["patch_size"]
        mi = np.array(position_ids(vc["image_size"], p, th // p, tw // p))
        print(f"    position_ids equal: {np.array_equal(ids[0], mi)}")

# ---- exact PyTorch CPU form (1 thread, C=3 -> cpu_upsample_linear_channels_last scalar tail, FMA-contracted)
def fma(a, b, c): return f32(np.float64(a) * np.float64(b) + np.float64(c))
def resize_exact(src, c, h, w, oh, ow):
    def coords(out, inp):
        scale = f32(f32(inp) / f32(out)); r = []
        for o in range(out):
            real = max(fma(scale, f32(f32(o) + f32(0.5)), f32(-0.5)), f32(0))
            i0 = min(int(np.floor(real)), inp - 1); i1 = i0 + (1 if i0 < inp - 1 else 0)
            l1 = f32(min(max(f32(real - f32(i0)), f32(0)), f32(1))); r.append((i0, i1, f32(f32(1) - l1), l1))
        return r
    ys, xs = coords(oh, h), coords(ow, w); out = np.zeros((c, oh, ow), f32)
    for ch in range(c):
        p = src[ch]
        for a, (y0, y1, h0, h1) in enumerate(ys):
            for b, (x0, x1, w0, w1) in enumerate(xs):
                s = fma(f32(h0 * w0), p[y0, x0], f32(f32(h0 * w1) * p[y0, x1]))
                s = fma(f32(h1 * w0), p[y1, x0], s)
                out[ch, a, b] = fma(f32(h1 * w1), p[y1, x1], s)
    return out

# ---- fedvla data crate (shared/data/src/image.rs): resize on u8 (round), later /255 -> policy
def resize_u8_path(img01, tw, th):
    c, h, w = img01.shape
    u8 = np.clip(np.round(img01 * 255), 0, 255)        # a u8 frame whose /255 is the float image
    ratio = max(w / tw, h / th); sw, sh = min(max(int(w / ratio), 1), tw), min(max(int(h / ratio), 1), th)
    def taps(out, inp):
        scale = inp / out; r = []
        for o in range(out):
            s = max((o + 0.5) * scale - 0.5, 0.0); i0 = min(int(np.floor(s)), inp - 1); r.append((i0, min(i0 + 1, inp - 1), f32(s - i0)))
        return r
    xs, ys = taps(sw, w), taps(sh, h); out = np.zeros((c, th, tw), f32)
    for ch in range(c):
        p = u8[ch].astype(f32)
        for yi, (y0, y1, fy) in enumerate(ys):
            for xi, (x0, x1, fx) in enumerate(xs):
                top = p[y0, x0] + (p[y0, x1] - p[y0, x0]) * fx; bot = p[y1, x0] + (p[y1, x1] - p[y1, x0]) * fx
                out[ch, th - sh + yi, tw - sw + xi] = np.clip(np.round(top + (bot - top) * fy), 0, 255)
    return (out / f32(255)) * f32(2) - f32(1), (u8 / 255).astype(f32)

print("\n== exact-form check, u8 data path, camera-order effect")
for d in sys.argv[1:]:
    cfg = json.load(open(f"{d}/config.json"))
    inp, out = load_file(f"{d}/inputs.safetensors"), load_file(f"{d}/outputs.safetensors")
    tw, th = cfg["resize_imgs_with_padding"]
    order = [k for k, v in cfg["input_features"].items() if v["type"] == "VISUAL"]
    for k in order:
        img = inp[k]; b, c, h, w = img.shape
        if (h, w) == (th, tw): continue
        ratio = max(w / tw, h / th); rh, rw = int(h / ratio), int(w / ratio)
        ex = np.zeros((b, c, th, tw), f32)
        for n in range(b): ex[n, :, th - rh:, tw - rw:] = resize_exact(img[n], c, h, w, rh, rw)
        ex = ex * f32(2) - f32(1)
        ref = out[f"prepared.images.{k}"]
        # u8 path vs LeRobot on the same u8-quantised frame
        u8p, q = resize_u8_path(img[0], tw, th)
        lr = np.zeros((c, th, tw), f32); lr[:, th - rh:, tw - rw:] = resize_exact(q, c, h, w, rh, rw); lr = lr * f32(2) - f32(1)
        print(f"  {d.split('/')[-1]} {k}: exact-form bitwise {np.array_equal(ex, ref)} (max {np.abs(ex.astype(np.float64) - ref).max():.2g});"
              f" u8 data path vs LeRobot float path max|diff| {np.abs(u8p - lr).max():.3g} (in [-1,1])")
    # prefix image part in fedvla's (sorted) order vs LeRobot's
    pe = out["fm.prefix_embs"]; n_tok = out[f"vision.{order[0]}.connector_out"].shape[1]
    dt = pe.shape[-1]
    def img_part(keys): return np.concatenate([out[f"vision.{kk}.connector_out"] * f32(np.sqrt(dt)) for kk in keys], 1)
    L = len(order) * n_tok
    d_lr = np.abs(img_part(order) - pe[:, :L]).max(); d_rs = np.abs(img_part(sorted(order)) - pe[:, :L]).max()
    print(f"  {d.split('/')[-1]}: prefix image part from vision.*.connector_out*sqrt(Dt): LeRobot order max|diff| {d_lr:.2g}; "
          f"sorted (fedvla) order max|diff| {d_rs:.3g}")
