//! The frozen-feature cache in the shared trainer on a shard the sim recorded: two rounds of local training with
//! the cache (in memory, or spilled to files) equal those without it (losses and updates to 1e-6), the second
//! round computes no row's context again, and a new trainer of the same weights and shard reads the spilled rows
//! back.

use fedvla_aggregator::config::{ComputeDevice, RunConfig};
use fedvla_federation::{LocalTrainer, RoundTask, StrategyParams, UpdateEncoding};
use fedvla_learner::SmolVlaTrainer;
use fedvla_workloads::datagen::{GenDataOptions, generate_dataset};
use fedvla_workloads::smolvla::SmolVlaWorkload;

fn task(round: u64) -> RoundTask {
    RoundTask {
        round,
        model_version: round - 1,
        local_steps: 6,
        batch_size: 4,
        lr: 1e-3,
        lr_schedule: None,
        seed: 40 + round,
        strategy: StrategyParams::plain("fedavg"),
        keep_optimizer_state: false,
        opening_frames: None,
        deadline_ms: 1,
        eval_request: false,
        rollout: None,
        update_encoding: UpdateEncoding::F32,
        model_deltas: None,
    }
}

fn workload(tmp: &std::path::Path) -> SmolVlaWorkload {
    let dataset = tmp.join("so100");
    generate_dataset(&dataset, &GenDataOptions { episodes: 4, image_size: 32, ..GenDataOptions::default() }, |_| {})
        .unwrap();
    let config = RunConfig::default()
        .with_overrides(&format!(
            "workload=smolvla model-size=tiny dataset={} num-clients=1 train-expert-only=true \
             freeze-vision-encoder=true",
            dataset.display()
        ))
        .unwrap();
    SmolVlaWorkload::prepare_centralized(&config, &tmp.join("shards")).unwrap()
}

/// Trains `cached` and `uncached` two rounds side by side, both from the same global model each round, and
/// checks they agree.
fn two_rounds_agree(cached: &mut SmolVlaTrainer, uncached: &mut SmolVlaTrainer) {
    let runtime = tokio::runtime::Builder::new_current_thread().build().unwrap();
    for round in 1..=2 {
        let (a, b) = runtime.block_on(async { (cached.train(&task(round)).await, uncached.train(&task(round)).await) });
        let (a, b) = (a.unwrap(), b.unwrap());
        assert!(
            (a.train_loss - b.train_loss).abs() <= 1e-6,
            "round {round}: {} against {}",
            a.train_loss,
            b.train_loss
        );
        for (name, t) in a.update.iter() {
            for (x, y) in t.values.iter().zip(&b.update.get(name).unwrap().values) {
                assert!((x - y).abs() <= 1e-6, "round {round}, {name}: {x} against {y}");
            }
        }
        // Both start the next round from the same global model, as a federation's clients do.
        cached.set_global(&a.update).unwrap();
        uncached.set_global(&a.update).unwrap();
    }
}

#[test]
fn training_with_the_cache_equals_training_without_it() {
    let tmp = tempfile::tempdir().unwrap();
    let workload = workload(tmp.path());
    let mut cached = workload.centralized_trainer(ComputeDevice::Cpu).unwrap();
    let mut uncached = workload.centralized_trainer(ComputeDevice::Cpu).unwrap().with_feature_cache(0);
    assert!(cached.feature_cache().is_some() && uncached.feature_cache().is_none());
    two_rounds_agree(&mut cached, &mut uncached);
    let cache = cached.feature_cache().unwrap();
    // 2 rounds x 6 steps x 4 rows: every row computed once, then served.
    assert_eq!(cache.hits + cache.misses, 48);
    assert!(cache.misses < 48 && cache.bytes() > 0, "{} misses", cache.misses);
}

#[test]
fn rows_beyond_the_memory_budget_spill_to_files_and_read_back() {
    let tmp = tempfile::tempdir().unwrap();
    let workload = workload(tmp.path());
    let spill_dir = tmp.path().join("features");
    // One byte of memory: every row goes to a file.
    let spilling = || {
        workload.centralized_trainer(ComputeDevice::Cpu).unwrap().with_feature_cache(1).spill_feature_cache(
            &spill_dir,
            "frozen",
            1 << 30,
        )
    };
    let mut cached = spilling();
    let mut uncached = workload.centralized_trainer(ComputeDevice::Cpu).unwrap().with_feature_cache(0);
    two_rounds_agree(&mut cached, &mut uncached);
    let cache = cached.feature_cache().unwrap();
    assert_eq!(cache.bytes(), 0);
    assert!(
        cache.spilled_bytes() > 0 && cache.hits > 0,
        "{} bytes spilled, {} hits",
        cache.spilled_bytes(),
        cache.hits
    );
    let distinct = cache.misses;
    // A new trainer of the same weights and shard (a restarted volunteer) computes nothing it spilled.
    let mut again = spilling();
    let mut uncached = workload.centralized_trainer(ComputeDevice::Cpu).unwrap().with_feature_cache(0);
    two_rounds_agree(&mut again, &mut uncached);
    let cache = again.feature_cache().unwrap();
    assert_eq!(cache.misses, 0, "rows computed again (of {distinct} the first trainer computed)");
    // Other frozen weights never read them.
    let other = workload.centralized_trainer(ComputeDevice::Cpu).unwrap().with_feature_cache(1).spill_feature_cache(
        &spill_dir,
        "other",
        1 << 30,
    );
    assert_eq!(other.feature_cache().unwrap().spilled_bytes(), 0);
}
