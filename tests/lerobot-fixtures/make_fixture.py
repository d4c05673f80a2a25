#!/usr/bin/env python3
"""Golden SmolVLA fixture made with the real LeRobot 0.6.1 code, in the layout of `smolvla-tiny-a`,
with any camera list (per-camera H x W) and model input size (`resize_imgs_with_padding`).

Run inside the lerobot-check chroot (see README.md next to this file):

    python3 make_fixture.py OUT --vlm-src .../smolvla-tiny-a/vlm \
        --camera observation.images.top=30x44 --camera observation.images.wrist=32x32 \
        [--resize 32x32] [--vision-image-size N] [--check-against DIR]

--camera NAME=HxW    one camera, in model order (= config.json input_features order); repeatable.
--resize WxH         resize_imgs_with_padding, stored (width, height) as LeRobot does; default 32x32.
--vision-image-size  vision_config.image_size written to OUT/vlm/config.json (default: keep the
                     source's). Position-embedding table = (image_size/patch)^2; a model input larger
                     than image_size makes SmolVLM bucket the patch coordinates onto that table.
--check-against DIR  compare every file's tensors with another fixture (bitwise report).

Recipe (reverse-engineered from smolvla-tiny-a and checked to reproduce it bitwise):
  * torch.use_deterministic_algorithms(True), 1 intra-op thread, CPU, float32.
  * config = the smolvla-tiny-a config.json fields (tiny sizes) with the given cameras / resize.
  * torch.manual_seed(0) right before SmolVLAPolicy(config); load_vlm_weights=False, VLM built from vlm/.
  * every parameter whose elements are all equal gets += randn(shape, generator=seed 2000) * 0.1,
    in named_parameters() order.
  * inputs from torch.Generator().manual_seed(1000), drawn in this order: one rand((B,3,H,W)) per
    camera (config order); state mean = randn(S); state std = rand(S)*1.5+0.5; action mean = randn(A);
    action std = rand(A)*1.5+0.5; raw state = randn(B,S)*std+mean; raw action = randn(B,T,A)*std+mean;
    noise = randn(B,T,Amax); sample_noise = randn(B,T,Amax). time = [0.3, 0.85] (cycled to B);
    action_is_pad: last 2 steps of element 1 (every odd element).
"""
import argparse
import json
import math
import os
import platform
import shutil
import sys
import time as _time

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

TINY_CONFIG = {
    "n_obs_steps": 1,
    "device": "cpu",
    "use_amp": False,
    "use_peft": False,
    "push_to_hub": False,
    "repo_id": None,
    "private": None,
    "tags": None,
    "license": None,
    "pretrained_path": None,
    "pretrained_revision": None,
    "chunk_size": 5,
    "n_action_steps": 5,
    "normalization_mapping": {"VISUAL": "IDENTITY", "STATE": "MEAN_STD", "ACTION": "MEAN_STD"},
    "max_state_dim": 8,
    "max_action_dim": 8,
    "empty_cameras": 0,
    "adapt_to_pi_aloha": False,
    "use_delta_joint_actions_aloha": False,
    "tokenizer_max_length": 48,
    "num_steps": 10,
    "use_cache": True,
    "freeze_vision_encoder": True,
    "train_expert_only": True,
    "train_state_proj": True,
    "optimizer_lr": 0.0001,
    "optimizer_betas": [0.9, 0.95],
    "optimizer_eps": 1e-08,
    "optimizer_weight_decay": 1e-10,
    "optimizer_grad_clip_norm": 10,
    "scheduler_warmup_steps": 1000,
    "scheduler_decay_steps": 30000,
    "scheduler_decay_lr": 2.5e-06,
    "vlm_model_name": "vlm",
    "load_vlm_weights": False,
    "add_image_special_tokens": False,
    "attention_mode": "cross_attn",
    "prefix_length": -1,
    "pad_language_to": "longest",
    "num_expert_layers": -1,
    "num_vlm_layers": 4,
    "self_attn_every_n_layers": 2,
    "expert_width_multiplier": 0.75,
    "min_period": 0.004,
    "max_period": 4.0,
    "rtc_config": None,
    "compile_model": False,
    "compile_mode": "max-autotune",
}

GRAD_KEYS = [
    "model.state_proj.weight",
    "model.state_proj.bias",
    "model.action_in_proj.weight",
    "model.action_out_proj.weight",
    "model.action_out_proj.bias",
    "model.action_time_mlp_in.weight",
    "model.vlm_with_expert.lm_expert.layers.0.self_attn.q_proj.weight",
    "model.vlm_with_expert.lm_expert.layers.1.self_attn.q_proj.weight",
    "model.vlm_with_expert.lm_expert.layers.1.self_attn.k_proj.weight",
    "model.vlm_with_expert.lm_expert.layers.3.mlp.down_proj.weight",
]


def parse_hw(s, sep="x"):
    a, b = s.lower().split(sep)
    return int(a), int(b)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--vlm-src", required=True, help="folder with the tiny VLM config + tokenizer (smolvla-tiny-a/vlm)")
    ap.add_argument("--camera", action="append", required=True, help="NAME=HxW (repeatable, model order)")
    ap.add_argument("--resize", default="32x32", help="resize_imgs_with_padding as WIDTHxHEIGHT")
    ap.add_argument("--vision-image-size", type=int, default=None)
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--task", default="pick up the red cube")
    ap.add_argument("--set-name", default=None, help="meta.json 'set' (default: basename of OUT)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--check-against", default=None)
    ap.add_argument("--force", action="store_true", help="overwrite a non-empty OUT")
    a = ap.parse_args()
    t_start = _time.time()

    cams = []
    for spec in a.camera:
        name, hw = spec.split("=")
        if not name.startswith("observation.images."):
            name = "observation.images." + name
        cams.append((name, parse_hw(hw)))
    rw, rh = parse_hw(a.resize)
    out = os.path.abspath(a.out)
    if os.path.exists(out) and os.listdir(out):
        if not a.force:
            raise SystemExit(f"{out} is not empty (use --force)")
        shutil.rmtree(out)
    os.makedirs(out, exist_ok=True)

    # ---- vlm/ folder (copied; optionally a different vision image_size)
    shutil.copytree(os.path.abspath(a.vlm_src), os.path.join(out, "vlm"))
    for fn in os.listdir(os.path.join(out, "vlm")):
        os.chmod(os.path.join(out, "vlm", fn), 0o644)
    if a.vision_image_size:
        p = os.path.join(out, "vlm", "config.json")
        vc = json.load(open(p))
        vc["vision_config"]["image_size"] = a.vision_image_size
        json.dump(vc, open(p, "w"), indent=2)
        p = os.path.join(out, "vlm", "processor_config.json")
        if os.path.isfile(p):
            pc = json.load(open(p))
            for k in ("size", "max_image_size"):
                if isinstance(pc.get("image_processor", {}).get(k), dict):
                    pc["image_processor"][k]["longest_edge"] = a.vision_image_size
            json.dump(pc, open(p, "w"), indent=2)
    os.chdir(out)  # vlm_model_name "vlm" resolves relative to the working directory

    import torch

    torch.use_deterministic_algorithms(True)
    torch.set_num_threads(a.threads)
    import draccus
    import lerobot
    import lerobot.policies  # noqa: F401
    import safetensors
    import tokenizers
    import transformers
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.common.vla_utils import create_sinusoidal_pos_embedding
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from lerobot.policies.smolvla.processor_smolvla import make_smolvla_pre_post_processors
    from safetensors.torch import save_file

    S, A = 6, 6
    B = a.batch
    cfg_dict = dict(TINY_CONFIG)
    feats = {"observation.state": {"type": "STATE", "shape": [S]}}
    for name, (h, w) in cams:
        feats[name] = {"type": "VISUAL", "shape": [3, h, w]}
    cfg_dict["input_features"] = feats
    cfg_dict["output_features"] = {"action": {"type": "ACTION", "shape": [A]}}
    cfg_dict["resize_imgs_with_padding"] = [rw, rh]
    cfg = draccus.decode(PreTrainedConfig.get_choice_class("smolvla"), cfg_dict)
    T, Amax, Smax = cfg.chunk_size, cfg.max_action_dim, cfg.max_state_dim

    # ---- 1. policy, perturbation, save
    torch.manual_seed(0)
    policy = SmolVLAPolicy(cfg)
    policy.eval()
    gp = torch.Generator().manual_seed(2000)
    perturbed = []
    with torch.no_grad():
        for name, p in policy.named_parameters():
            flat = p.detach().flatten()
            if flat.numel() > 0 and bool((flat == flat[0]).all()):
                p.add_(torch.randn(p.shape, generator=gp) * 0.1)
                perturbed.append(name)
    policy.save_pretrained(out)
    # save_pretrained writes config.json from the config; keep the exact order of input_features.

    # ---- 2. inputs, pre-processor
    g = torch.Generator().manual_seed(1000)
    images = {name: torch.rand((B, 3, h, w), generator=g) for name, (h, w) in cams}
    s_mean = torch.randn(S, generator=g)
    s_std = torch.rand(S, generator=g) * 1.5 + 0.5
    a_mean = torch.randn(A, generator=g)
    a_std = torch.rand(A, generator=g) * 1.5 + 0.5
    raw_state = torch.randn((B, S), generator=g) * s_std + s_mean
    raw_action = torch.randn((B, T, A), generator=g) * a_std + a_mean
    noise = torch.randn((B, T, Amax), generator=g)
    sample_noise = torch.randn((B, T, Amax), generator=g)
    times = torch.tensor([[0.3, 0.85][i % 2] for i in range(B)], dtype=torch.float32)
    action_is_pad = torch.zeros((B, T), dtype=torch.bool)
    for i in range(1, B, 2):
        action_is_pad[i, T - 2:] = True
    tasks = [a.task] * B
    stats = {"observation.state": {"mean": s_mean, "std": s_std}, "action": {"mean": a_mean, "std": a_std}}
    pre, post = make_smolvla_pre_post_processors(cfg, dataset_stats=stats)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    raw = {"observation.state": raw_state.clone(), "action": raw_action.clone(), "task": list(tasks)}
    raw.update({k: v.clone() for k, v in images.items()})
    pb = pre(raw)
    batch = {k: v for k, v in pb.items() if torch.is_tensor(v)}
    for k in images:
        assert torch.equal(batch[k], images[k]), f"pre-processor changed {k}"
    batch["action_is_pad"] = action_is_pad
    tok = batch["observation.language.tokens"]
    att = batch["observation.language.attention_mask"].bool()
    inputs = {
        "observation.state": batch["observation.state"].contiguous(),
        "action": batch["action"].contiguous(),
        "action_is_pad": action_is_pad,
        "observation.language.tokens": tok.to(torch.int64).contiguous(),
        "observation.language.attention_mask": att.contiguous(),
        "noise": noise,
        "sample_noise": sample_noise,
        "time": times,
        "raw.observation.state": raw_state,
        "raw.action": raw_action,
        "stats.observation.state.mean": s_mean,
        "stats.observation.state.std": s_std,
        "stats.action.mean": a_mean,
        "stats.action.std": a_std,
    }
    inputs.update(images)
    batch["observation.language.attention_mask"] = att
    save_file(inputs, os.path.join(out, "inputs.safetensors"))

    O = {}
    model = policy.model
    vwe = model.vlm_with_expert
    vm = vwe.get_vlm_model()

    def model_batch():
        return {k: (v.clone() if torch.is_tensor(v) else v) for k, v in batch.items() if k.startswith("observation.") or k in ("action", "action_is_pad")}

    # ---- prepared.*
    b0 = model_batch()
    pimgs, pmasks = policy.prepare_images(b0)
    pstate = policy.prepare_state(b0)
    pactions = policy.prepare_action(b0)
    cam_order = [k for k in cfg.image_features if k in b0]
    for k, im in zip(cam_order, pimgs):
        O[f"prepared.images.{k}"] = im.contiguous()
    O["prepared.img_masks"] = torch.stack(pmasks, 0).contiguous()
    O["prepared.state"] = pstate.contiguous()
    O["prepared.actions"] = pactions.contiguous()
    lang_tokens, lang_masks = b0["observation.language.tokens"], b0["observation.language.attention_mask"]

    # ---- 3. flow-matching forward with hooks (train mode)
    policy.train()
    rec = {"vlm_in": [], "exp_in": [], "vis": [], "conn": [], "pos": [], "prefix_out": None, "suffix_out": None}
    hooks = []
    for layer in vm.text_model.layers:
        hooks.append(layer.input_layernorm.register_forward_pre_hook(lambda m, i: rec["vlm_in"].append(i[0].detach().clone())))
    for layer in vwe.lm_expert.layers:
        hooks.append(layer.input_layernorm.register_forward_pre_hook(lambda m, i: rec["exp_in"].append(i[0].detach().clone())))
    hooks.append(vm.text_model.norm.register_forward_hook(lambda m, i, o: rec.__setitem__("prefix_out", o.detach().clone())))
    hooks.append(vwe.lm_expert.norm.register_forward_hook(lambda m, i, o: rec.__setitem__("suffix_out", o.detach().clone())))
    hooks.append(vm.vision_model.register_forward_hook(lambda m, i, o: rec["vis"].append(o.last_hidden_state.detach().clone())))
    hooks.append(vm.connector.register_forward_hook(lambda m, i, o: rec["conn"].append(o.detach().clone())))
    hooks.append(vm.vision_model.embeddings.position_embedding.register_forward_pre_hook(lambda m, i: rec["pos"].append(i[0].detach().clone())))
    v_out = []
    hooks.append(model.action_out_proj.register_forward_hook(lambda m, i, o: v_out.append(o.detach().clone())))

    orig = {}

    def wrap(obj, name, fn):
        orig[(id(obj), name)] = (obj, name)
        inner = getattr(obj, name)
        setattr(obj, name, lambda *args, **kw: fn(inner, *args, **kw))

    def unwrap_all():
        for obj, name in orig.values():
            delattr(obj, name)
        orig.clear()

    cap = {}

    def rec_prefix(inner, *args, **kw):
        r = inner(*args, **kw)
        cap["prefix"] = tuple(t.detach().clone() for t in r)
        return r

    def rec_suffix(inner, noisy_actions, timestep):
        r = inner(noisy_actions, timestep)
        cap.setdefault("x_t", noisy_actions.detach().clone())
        cap["suffix"] = tuple(t.detach().clone() for t in r)
        return r

    def rec_vwe(inner, *args, **kw):
        cap["att_2d"] = kw["attention_mask"].detach().clone()
        cap["pos_ids"] = kw["position_ids"].detach().clone()
        return inner(*args, **kw)

    wrap(model, "embed_prefix", rec_prefix)
    wrap(model, "embed_suffix", rec_suffix)
    wrap(vwe, "forward", rec_vwe)
    with torch.no_grad():
        losses = model.forward(pimgs, pmasks, lang_tokens, lang_masks, pstate, pactions, noise.clone(), times.clone())
    unwrap_all()
    for h in hooks:
        h.remove()
    n_vlm, n_exp = len(vm.text_model.layers), len(vwe.lm_expert.layers)
    assert len(rec["vlm_in"]) == n_vlm and len(rec["exp_in"]) == n_exp, (len(rec["vlm_in"]), len(rec["exp_in"]))
    assert len(rec["vis"]) == len(cam_order)
    for i, k in enumerate(cam_order):
        O[f"vision.{k}.last_hidden_state"] = rec["vis"][i].contiguous()
        O[f"vision.{k}.connector_out"] = rec["conn"][i].contiguous()
        O[f"vision.{k}.position_ids"] = rec["pos"][i].to(torch.int64).contiguous()
    pe, ppm, pam = cap["prefix"]
    se, spm, sam = cap["suffix"]
    O["fm.prefix_embs"], O["fm.prefix_pad_masks"], O["fm.prefix_att_masks"] = pe.contiguous(), ppm.contiguous(), pam.contiguous()
    O["fm.suffix_embs"], O["fm.suffix_pad_masks"], O["fm.suffix_att_masks"] = se.contiguous(), spm.contiguous(), sam.contiguous()
    O["fm.att_2d_masks"] = cap["att_2d"].contiguous()
    O["fm.position_ids"] = cap["pos_ids"].contiguous()
    O["fm.vlm_layer_inputs"] = torch.stack(rec["vlm_in"], 0).contiguous()
    O["fm.expert_layer_inputs"] = torch.stack(rec["exp_in"], 0).contiguous()
    O["fm.prefix_out"] = rec["prefix_out"].contiguous()
    O["fm.suffix_out"] = rec["suffix_out"][:, -T:].contiguous()
    O["fm.x_t"] = cap["x_t"].contiguous()
    O["fm.u_t"] = (noise - pactions).contiguous()
    O["fm.v_t"] = v_out[-1].contiguous()
    O["fm.losses"] = losses.detach().contiguous()
    O["fm.time_emb"] = create_sinusoidal_pos_embedding(
        times, vwe.expert_hidden_size, cfg.min_period, cfg.max_period, device=torch.device("cpu")
    ).type(torch.float32).contiguous()

    # ---- 4. sampling (eval mode)
    policy.eval()
    scap = {"calls": [], "x": [], "v": [], "t": []}

    def rec_vwe_s(inner, *args, **kw):
        r = inner(*args, **kw)
        embeds = kw["inputs_embeds"]
        if embeds[1] is None:  # prefix prefill
            scap["prefix_mask"] = kw["attention_mask"].detach().clone()
            scap["prefix_pos"] = kw["position_ids"].detach().clone()
            cache = r[1]
            scap["keys"] = torch.stack([cache.layers[l].keys.detach().clone() for l in range(n_vlm)], 0)
            scap["values"] = torch.stack([cache.layers[l].values.detach().clone() for l in range(n_vlm)], 0)
        else:
            scap.setdefault("den_mask", kw["attention_mask"].detach().clone())
            scap.setdefault("den_pos", kw["position_ids"].detach().clone())
        return r

    def rec_denoise(inner, *args, **kw):
        scap["x"].append(kw["x_t"].detach().clone())
        scap["t"].append(kw["timestep"].detach().clone()[0])
        v = inner(*args, **kw)
        scap["v"].append(v.detach().clone())
        return v

    wrap(vwe, "forward", rec_vwe_s)
    wrap(model, "denoise_step", rec_denoise)
    with torch.no_grad():
        actions = model.sample_actions(pimgs, pmasks, lang_tokens, lang_masks, pstate, noise=sample_noise.clone())
    unwrap_all()
    O["sample.actions"] = actions.contiguous()
    O["sample.prefix_att_2d_masks"] = scap["prefix_mask"].contiguous()
    O["sample.prefix_position_ids"] = scap["prefix_pos"].contiguous()
    O["sample.denoise_att_2d_masks"] = scap["den_mask"].contiguous()
    O["sample.denoise_position_ids"] = scap["den_pos"].contiguous()
    O["sample.prefix_kv.keys"] = scap["keys"].contiguous()
    O["sample.prefix_kv.values"] = scap["values"].contiguous()
    O["sample.time"] = torch.stack(scap["t"]).to(torch.float32).contiguous()
    O["sample.v_t"] = torch.stack(scap["v"], 0).contiguous()
    O["sample.x_t"] = torch.stack(scap["x"] + [actions], 0).contiguous()

    policy.reset()
    obs = {k: v for k, v in model_batch().items() if k not in ("action", "action_is_pad")}
    with torch.no_grad():
        chunk = policy.predict_action_chunk(obs, noise=sample_noise.clone())
    O["policy.predict_action_chunk"] = chunk.contiguous()
    O["policy.predict_action_chunk.unnormalized"] = post(chunk.clone()).contiguous()

    # ---- 5. loss, backward, clip, AdamW
    policy.train()
    policy.zero_grad(set_to_none=True)
    loss, loss_dict = policy.forward(model_batch(), noise=noise.clone(), time=times.clone())
    loss.backward()
    named = dict(policy.named_parameters())
    O["policy.loss"] = loss.detach().clone()
    loss_value = loss.item()
    for k in GRAD_KEYS:
        O[f"grad.{k}"] = named[k].grad.detach().clone().contiguous()
    gn = torch.nn.utils.clip_grad_norm_(policy.parameters(), cfg.optimizer_grad_clip_norm)
    O["grad_norm_total_preclip"] = gn.detach().clone().to(torch.float32)
    for k in GRAD_KEYS:
        O[f"grad_clipped.{k}"] = named[k].grad.detach().clone().contiguous()
    opt = cfg.get_optimizer_preset().build(policy.get_optim_params())
    opt.step()
    for k in GRAD_KEYS:
        O[f"adamw_step1.{k}"] = named[k].detach().clone().contiguous()
    save_file(O, os.path.join(out, "outputs.safetensors"))

    # ---- meta.json + README.md
    def count(mod):
        return {"total": sum(p.numel() for p in mod.parameters()), "trainable": sum(p.numel() for p in mod.parameters() if p.requires_grad)}

    tokzr = vwe.processor.tokenizer
    proj = [model.state_proj, model.action_in_proj, model.action_out_proj, model.action_time_mlp_in, model.action_time_mlp_out]
    # note: the counts below are taken after the optimizer step; requires_grad is unchanged by it
    meta = {
        "set": a.set_name or os.path.basename(out),
        "seed": 0,
        "batch_size": B,
        "state_dim": S,
        "action_dim": A,
        "camera_order": cam_order,
        "camera_input_shapes_chw": {k: [3, h, w] for k, (h, w) in cams},
        "resize_imgs_with_padding_wh": [rw, rh],
        "vision_image_size": vm.vision_model.config.image_size,
        "tasks": tasks,
        "tasks_after_newline_step": [t if t.endswith("\n") else t + "\n" for t in tasks],
        "token_strings": [tokzr.convert_ids_to_tokens(row[m].tolist()) for row, m in zip(tok, att)],
        "time": [[0.3, 0.85][i % 2] for i in range(B)],
        "weights_perturbed_keys": perturbed,
        "weights_perturb_std": 0.1,
        "param_counts": {
            "total": sum(p.numel() for p in policy.parameters()),
            "trainable": sum(p.numel() for p in policy.parameters() if p.requires_grad),
            "by_module": {
                "vision_model": count(vm.vision_model),
                "connector": count(vm.connector),
                "text_model": count(vm.text_model),
                "lm_head": count(vwe.vlm.lm_head),
                "lm_expert": count(vwe.lm_expert),
                "projections": {
                    "total": sum(p.numel() for m in proj for p in m.parameters()),
                    "trainable": sum(p.numel() for m in proj for p in m.parameters() if p.requires_grad),
                },
            },
            "trainable_keys": [k for k, p in policy.named_parameters() if p.requires_grad],
        },
        "expert": {
            "hidden_size": vwe.expert_hidden_size,
            "intermediate_size": vwe.lm_expert.config.intermediate_size,
            "num_layers": n_exp,
        },
        "expert_layer_kinds": ["SA" if (cfg.self_attn_every_n_layers > 0 and l % cfg.self_attn_every_n_layers == 0) else "CA" for l in range(n_exp)],
        "vision_attn_implementation": getattr(vm.vision_model.config, "_attn_implementation", None),
        "versions": {
            "lerobot": lerobot.__version__ if hasattr(lerobot, "__version__") else "0.6.1",
            "torch": torch.__version__,
            "transformers": transformers.__version__,
            "tokenizers": tokenizers.__version__,
            "safetensors": safetensors.__version__,
            "python": platform.python_version(),
            "platform": platform.platform(),
        },
        "policy_forward_loss_dict": loss_dict,
        "grad_keys": GRAD_KEYS,
        "optimizer": {"class": type(opt).__name__, **{k: opt.defaults[k] for k in ("lr", "betas", "eps", "weight_decay", "amsgrad", "maximize", "capturable", "differentiable", "decoupled_weight_decay") if k in opt.defaults}},
        "grad_clip_norm": cfg.optimizer_grad_clip_norm,
        "grad_clip_active": bool(float(gn) > cfg.optimizer_grad_clip_norm),
        "policy_loss": loss_value,
        "grad_norm_total_preclip": float(gn),
        "generator": "fedvla tests/lerobot-fixtures/make_fixture.py " + " ".join(sys.argv[1:]),
    }
    if isinstance(meta["optimizer"].get("betas"), tuple):
        meta["optimizer"]["betas"] = list(meta["optimizer"]["betas"])
    json.dump(meta, open(os.path.join(out, "meta.json"), "w"), indent=2)

    lines = [
        f"# SmolVLA tiny golden fixture `{meta['set']}` (LeRobot {meta['versions']['lerobot']})",
        "",
        "Made by `tests/lerobot-fixtures/make_fixture.py` (fedvla) with the same recipe, tiny config and",
        "file layout as the public `smolvla-tiny-a` fixture (see its README for every tensor's meaning);",
        "only the cameras and the model input size differ.",
        "",
        f"- command: `{meta['generator']}`",
        f"- cameras (model order = config.json input_features order): "
        + ", ".join(f"`{k}` {h}x{w} (HxW)" for k, (h, w) in cams),
        f"- resize_imgs_with_padding (W, H) = ({rw}, {rh}); vision image_size {meta['vision_image_size']}, "
        f"patch {vm.vision_model.config.patch_size}",
        f"- policy.loss = {loss_value:.8f}; grad_norm_total_preclip = {float(gn):.8f}",
        f"- versions: {json.dumps(meta['versions'])}",
        "",
        "Image path in LeRobot (SmolVLAPolicy.prepare_images -> vla_utils.resize_with_pad): images are float32",
        "[B,3,H,W] in [0,1]; if (H,W) != (Ht,Wt): ratio = max(W/Wt, H/Ht), resized = (int(H/ratio), int(W/ratio)),",
        "F.interpolate(mode='bilinear', align_corners=False, antialias=False), then F.pad(value=0) on the LEFT",
        "(Wt-w columns) and TOP (Ht-h rows); then x*2-1 (padding -> -1). Exactly-sized images are returned",
        "untouched. Cameras in config.input_features order.",
        "",
        "| file | tensors |",
        "|---|---|",
        f"| inputs.safetensors | {len(inputs)} |",
        f"| outputs.safetensors | {len(O)} |",
        "",
        "outputs.safetensors:",
        "",
        "| name | shape | dtype |",
        "|---|---|---|",
    ]
    for k in sorted(O):
        lines.append(f"| `{k}` | {list(O[k].shape)} | {str(O[k].dtype).replace('torch.', '')} |")
    open(os.path.join(out, "README.md"), "w").write("\n".join(lines) + "\n")
    dt = _time.time() - t_start
    print(f"MAKE_FIXTURE OK {out}: cameras={[(k, h, w) for k, (h, w) in cams]} resize=({rw},{rh}) "
          f"inputs={len(inputs)} outputs={len(O)} loss={loss_value:.8f} in {dt:.1f}s")

    if a.check_against:
        compare(out, os.path.abspath(a.check_against))


def compare(mine, ref):
    import torch
    from safetensors.torch import load_file

    worst = 0.0
    bad = []
    for fn in ("model.safetensors", "inputs.safetensors", "outputs.safetensors",
               "policy_preprocessor_step_5_normalizer_processor.safetensors",
               "policy_postprocessor_step_0_unnormalizer_processor.safetensors"):
        A_, B_ = load_file(os.path.join(mine, fn)), load_file(os.path.join(ref, fn))
        if set(A_) != set(B_):
            bad.append(f"{fn}: key sets differ: only mine {sorted(set(A_) - set(B_))[:5]}, only ref {sorted(set(B_) - set(A_))[:5]}")
        nbit = 0
        fw = 0.0
        for k in sorted(set(A_) & set(B_)):
            x, y = A_[k], B_[k]
            if x.shape != y.shape or x.dtype != y.dtype:
                bad.append(f"{fn}:{k}: {tuple(x.shape)} {x.dtype} vs {tuple(y.shape)} {y.dtype}")
                continue
            if torch.equal(x, y):
                nbit += 1
                continue
            d = float((x.double() - y.double()).abs().max())
            fw = max(fw, d)
            bad.append(f"{fn}:{k}: max|diff| {d:.3g}")
        worst = max(worst, fw)
        print(f"compare {fn}: {nbit}/{len(B_)} tensors bitwise equal, max|diff| {fw:.3g}")
    for fn in ("config.json", "policy_preprocessor.json", "policy_postprocessor.json"):
        same = json.load(open(os.path.join(mine, fn))) == json.load(open(os.path.join(ref, fn)))
        print(f"compare {fn}: {'same' if same else 'DIFFERENT'}")
        if not same:
            bad.append(fn)
    for line in bad[:40]:
        print("  diff:", line)
    print(f"COMPARE {'BITWISE' if not bad else 'DIFF'} {mine} vs {ref}: worst {worst:.3g}")


if __name__ == "__main__":
    main()
