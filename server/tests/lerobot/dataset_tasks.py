#!/usr/bin/env python3
"""What LeRobot 0.6.1 makes of a multi-task dataset's tasks (run inside the lerobot-check chroot, through its run.sh).

usage: python3 dataset_tasks.py DIR EXPECTED_JSON
  EXPECTED_JSON: a JSON list, the instruction of each episode in episode order.

Loads DIR with LeRobotDataset and checks that its metadata lists exactly the distinct expected instructions
(meta.total_tasks, meta.tasks), that every episode's row in meta/episodes names its own, and that the first and
last frame of every episode come out of the dataset with that episode's task string. Exits 1 on a mismatch; the
last line is `CHECK_TASKS OK|FAIL ...`.
"""
import json
import os
import sys

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")

from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402


def main(root, expected):
    problems = []
    ds = LeRobotDataset("local/check", root=root, video_backend="pyav")
    distinct = sorted(set(expected))
    listed = sorted(ds.meta.tasks.index)
    if ds.meta.total_tasks != len(distinct) or listed != distinct:
        problems.append(f"tasks: total_tasks={ds.meta.total_tasks} listed {listed}, expected {distinct}")
    if ds.num_episodes != len(expected):
        problems.append(f"{ds.num_episodes} episodes, expected {len(expected)}")
    frames = 0
    for episode, instruction in enumerate(expected[: ds.num_episodes]):
        row = ds.meta.episodes[episode]
        if list(row["tasks"]) != [instruction]:
            problems.append(f"episode {episode}: meta/episodes tasks {row['tasks']}, expected {[instruction]}")
        for index in (row["dataset_from_index"], row["dataset_to_index"] - 1):
            item = ds[int(index)]
            frames += 1
            if int(item["episode_index"]) != episode or item["task"] != instruction:
                problems.append(
                    f"frame {index}: episode {int(item['episode_index'])} task {item['task']!r}, "
                    f"expected episode {episode} task {instruction!r}"
                )
    for p in problems:
        print(f"  FAIL: {p}")
    status = "FAIL" if problems else "OK"
    print(f"CHECK_TASKS {status} {root}: tasks={ds.meta.total_tasks} episodes={ds.num_episodes} frames_checked={frames}")
    return not problems


if __name__ == "__main__":
    sys.exit(0 if main(sys.argv[1], json.loads(sys.argv[2])) else 1)
