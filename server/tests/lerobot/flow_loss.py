#!/usr/bin/env python3
"""LeRobot 0.6.1's flow-matching loss of a SmolVLA policy directory on one frame of a LeRobot dataset, with given
noise and time, everything as `lerobot-train` prepares it (run inside the lerobot-check chroot, through its run.sh).

usage: python3 flow_loss.py POLICY_DIR DATASET_DIR INDEX NOISE
  INDEX: the dataset frame (global index) the batch of one is made of.
  NOISE: a safetensors file holding the flow-matching `noise` [1, chunk_size, max_action_dim] and `time` [1], and
         the frame's image of each camera (named by its feature, RGB uint8 [height, width, 3]), which replace the
         ones PyAV decodes (its YUV to RGB conversion rounds otherwise: a difference of decoders, not of policies).

The policy is POLICY_DIR's config.json with the dataset's cameras as its image features (what LeRobot's
make_policy makes of a dataset's features, and what our workload's policy configuration does: the cameras of
smolvla_base are not the dataset's), its vlm/ folder as the backbone, every weight from model.safetensors
(load_vlm_weights off). The batch is the frame as LeRobotDataset serves it to lerobot-train (its action chunk of
chunk_size steps from delta_timestamps, padded past the episode end, video decoded by pyav), collated, and sent
through POLICY_DIR's saved pre-processor with lerobot-train's overrides (normalisation with the dataset's
meta/stats.json; the tokenizer of vlm/). SmolVLAPolicy.forward(batch, noise, time) then runs in train mode without
gradients on the CPU, in float32. The last line printed is `FLOW_LOSS <loss>`.
"""
import os
import sys

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

import json  # noqa: E402

import draccus  # noqa: E402
import torch  # noqa: E402
import lerobot.policies  # noqa: E402,F401  (registers the policy config choices)
from lerobot.configs.policies import PreTrainedConfig  # noqa: E402
from lerobot.configs.types import FeatureType  # noqa: E402
from lerobot.datasets.factory import resolve_delta_timestamps  # noqa: E402
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata  # noqa: E402
from lerobot.utils.feature_utils import dataset_to_policy_features  # noqa: E402
from lerobot.policies.factory import make_pre_post_processors  # noqa: E402
from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy  # noqa: E402
from lerobot.utils.collate import lerobot_collate_fn  # noqa: E402
from safetensors.torch import load_file  # noqa: E402


def main(policy_dir, dataset_dir, index, noise_file):
    policy_dir, dataset_dir = os.path.abspath(policy_dir), os.path.abspath(dataset_dir)
    vlm_dir = os.path.join(policy_dir, "vlm")
    fields = json.load(open(os.path.join(policy_dir, "config.json")))
    fields.pop("type")
    # Python 3.14 breaks PreTrainedConfig.from_pretrained inside draccus' argparse; decoding the same JSON with
    # draccus is what it would do (as the checker's check_policy.py does).
    fields.update(vlm_model_name=vlm_dir, load_vlm_weights=False, device="cpu")
    config = draccus.decode(PreTrainedConfig.get_choice_class("smolvla"), fields)
    meta = LeRobotDatasetMetadata("local/rehearsal", root=dataset_dir)
    cameras = {k: f for k, f in dataset_to_policy_features(meta.features).items() if f.type is FeatureType.VISUAL}
    config.input_features = {
        **{k: f for k, f in config.input_features.items() if f.type is not FeatureType.VISUAL},
        **cameras,
    }
    policy = SmolVLAPolicy.from_pretrained(policy_dir, config=config)

    dataset = LeRobotDataset(
        "local/rehearsal",
        root=dataset_dir,
        delta_timestamps=resolve_delta_timestamps(config, meta),
        video_backend="pyav",
    )
    preprocessor, _ = make_pre_post_processors(
        config,
        pretrained_path=policy_dir,
        preprocessor_overrides={
            "device_processor": {"device": "cpu"},
            "normalizer_processor": {
                "stats": dataset.meta.stats,
                "features": {**config.input_features, **config.output_features},
                "norm_map": config.normalization_mapping,
            },
            "rename_observations_processor": {"rename_map": {}},
            "tokenizer_processor": {"tokenizer_name": vlm_dir},
        },
    )
    frame = dataset[index]
    given = load_file(noise_file)
    # The camera images the caller decoded (RGB uint8, height x width x 3), as LeRobotDataset serves a frame:
    # float32 channels-first in [0, 1].
    for camera in cameras:
        assert given[camera].shape[:2] == frame[camera].shape[1:], (camera, given[camera].shape, frame[camera].shape)
        differs = (given[camera].permute(2, 0, 1).float() - frame[camera] * 255).abs().max()
        print(f"{camera}: PyAV's decoding differs from the given image by at most {float(differs):.1f} levels")
        frame[camera] = given[camera].permute(2, 0, 1).float() / 255
    batch = preprocessor(lerobot_collate_fn([frame]))
    policy.train()
    with torch.no_grad():
        loss, _ = policy.forward(batch, noise=given["noise"], time=given["time"])
    pad = frame["action_is_pad"]
    print(f"frame {index} of episode {int(frame['episode_index'])}: {int((~pad).sum())} of {len(pad)} action steps "
          f"in the episode, {int(batch['observation.language.attention_mask'].sum())} task tokens")
    print(f"FLOW_LOSS {float(loss):.9g}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4])
