//! Shards: build from a dataset + partition, read back equal to the source rows, detect tampering.

mod common;

use fedvla_data::{
    ClientShard, DataError, LeRobotDataset, PartitionConfig, PartitionStrategy, ShardSpec, build_shard, episode_tasks,
    partition, verify_shard_file,
};

fn word_tokenizer(text: &str) -> Vec<u32> {
    text.split_whitespace().map(|w| w.bytes().map(u32::from).sum()).collect()
}

const SPEC: ShardSpec = ShardSpec { image_width: 16, image_height: 16, tokenizer_max_length: 8, pad_token_id: 0 };

#[test]
fn shard_round_trip_and_checksums() {
    let dir = common::temp_dir("shard");
    let root = common::write_dataset(&dir, "ds", &common::episodes(4, 12, 32), 32);
    let ds = LeRobotDataset::open(&root).expect("open");
    let config = PartitionConfig {
        num_clients: 2,
        strategy: PartitionStrategy::EpisodeModulo,
        client_held_out_fraction: 0.5,
        server_held_out_fraction: 0.0,
        seed: 7,
    };
    let parts = partition(&episode_tasks(&ds), &config).expect("partition");
    let out = dir.join("shards/client-000.safetensors");
    let mut packed = Vec::new();
    let sidecar =
        build_shard(&ds, &parts, 0, &SPEC, Some(&word_tokenizer), &out, &mut |e| packed.push(e.episode_index))
            .expect("build");
    assert_eq!(packed, [0, 2], "progress is told of every episode packed, in order");

    assert_eq!(sidecar.file_bytes, std::fs::metadata(&out).expect("stat").len());
    verify_shard_file(&out, &sidecar).expect("fresh file verifies");
    let written: fedvla_data::ShardFileManifest =
        serde_json::from_str(&std::fs::read_to_string(dir.join("shards/client-000.manifest.json")).expect("sidecar"))
            .expect("json");
    assert_eq!(written, sidecar);

    let shard = ClientShard::read(&out).expect("read");
    assert_eq!(shard.manifest, sidecar.manifest);
    // Client 0 of a modulo split over episodes 0..4 holds episodes 0 and 2, one of them held out.
    assert_eq!(shard.episodes.iter().map(|e| e.episode_index).collect::<Vec<_>>(), vec![0, 2]);
    assert_eq!(shard.episodes.iter().filter(|e| e.held_out).count(), 1);
    assert_eq!(shard.manifest.num_frames, 24);
    for e in &shard.episodes {
        let meta = &ds.episodes()[e.episode_index];
        for (row, global) in (e.start..e.end).zip(meta.dataset_from_index..meta.dataset_to_index) {
            assert_eq!(&shard.state[row * 6..row * 6 + 6], ds.vector("observation.state", global).expect("row"));
            assert_eq!(&shard.action[row * 6..row * 6 + 6], ds.vector("action", global).expect("row"));
            assert_eq!(shard.manifest.tasks[shard.task_index[row] as usize], meta.tasks[0]);
        }
    }
    for camera in ["observation.images.top", "observation.images.wrist"] {
        assert_eq!(shard.images[camera].len(), 24 * 16 * 16 * 3);
        assert!(shard.image(camera, 23).is_some_and(|img| img.iter().any(|&v| v != img[0])), "images carry content");
    }
    let (chunk, pad) = shard.action_chunk(10, 5).expect("row in an episode");
    assert_eq!(pad, vec![false, false, true, true, true]);
    assert_eq!(&chunk[4 * 6..5 * 6], &shard.action[11 * 6..12 * 6], "padding repeats the last action");
    let (tokens, mask) = shard.task_tokens.clone().expect("tokenized");
    assert_eq!(tokens.len(), shard.manifest.tasks.len() * 8);
    assert_eq!(mask[..8].iter().filter(|&&m| m == 1).count(), word_tokenizer(&shard.manifest.tasks[0]).len().min(8));
    let mean = &shard.stats["observation.state"]["mean"];
    let expected: Vec<f32> = ds.stats().expect("stats")["observation.state"].mean.iter().map(|&v| v as f32).collect();
    assert_eq!(mean, &expected);

    // Flip one byte of tensor data: both checks catch it.
    let mut bytes = std::fs::read(&out).expect("read");
    let last = bytes.len() - 1;
    bytes[last] ^= 0x55;
    std::fs::write(&out, &bytes).expect("write");
    assert!(matches!(ClientShard::read(&out), Err(DataError::ChecksumMismatch { .. })));
    assert!(matches!(verify_shard_file(&out, &sidecar), Err(DataError::ChecksumMismatch { .. })));
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
