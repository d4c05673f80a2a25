//! A server killed after round 1 and restarted with resume finishes round 2: no round lost or counted twice.

mod common;

use common::*;
use fedvla_aggregator::records::read_metrics;
use fedvla_aggregator::run_dir::{MODELS_DIR, RunDir, TRAINABLE_FILE, numbered_dirs};
use fedvla_federation::TrainOutput;

#[tokio::test]
async fn killed_after_round_one_then_resumed() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let dir = run_dir.path().to_owned();

    // First life: clients hang in round 2, so the kill lands while round 2 is in flight.
    let handle = start(cfg, run_dir).await;
    let clients: Vec<_> = (0..3).map(|shard| spawn_client(&handle, shard, Some(2))).collect();
    wait_status(&handle, |s| s.completed_rounds == 1).await;
    handle.kill().await;
    for (task, _) in &clients {
        task.abort();
    }
    let round_one = std::fs::read(dir.join("global_model/round_1").join(TRAINABLE_FILE)).unwrap();
    let rounds = |dir| metrics_lines(dir).iter().map(|l| l.round).collect::<Vec<_>>();
    assert_eq!(rounds(&dir), [0, 1]);

    // Second life: resume from the run directory, as `fedvla serve --resume` does.
    let (run_dir, cfg) = RunDir::open(&dir).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    assert_eq!(handle.status().borrow().completed_rounds, 1);
    let clients: Vec<_> = (0..3).map(|shard| spawn_client(&handle, shard, None)).collect();
    let status = handle.finish().await.unwrap();
    assert_eq!(status.completed_rounds, 2);
    let mut updates: Vec<TrainOutput> = Vec::new();
    for (task, rec) in clients {
        let summary = task.await.unwrap().unwrap();
        assert_eq!(summary.rounds_trained, 1, "resumed clients train round 2 only");
        updates.extend(rec.lock().unwrap().iter().map(|(round, u)| {
            assert_eq!(*round, 2);
            u.clone()
        }));
    }
    assert_eq!(rounds(&dir), [0, 1, 2]);
    assert_eq!(std::fs::read(dir.join("global_model/round_1").join(TRAINABLE_FILE)).unwrap(), round_one);
    let crc = |round: usize| metrics_lines(&dir)[round].model_crc32;
    assert_eq!(crc(1), run_dir.load_model(1).unwrap().checksum());
    assert_eq!(crc(2), run_dir.load_model(2).unwrap().checksum());
    assert_close(&run_dir.load_model(2).unwrap(), &weighted_mean(&updates), 1e-6);
    // Round 2 started from round 1's model: only version 1 was served, and the clients fetched it.
    assert_eq!(metrics_lines(&dir)[2].model_version, 2);
    let loss = |i: usize| heldout_loss(&metrics_lines(&dir)[i]);
    assert!(loss(2) < loss(1), "round 2 built on round 1");
}

/// Under `keep-models=evaluated` the models of rounds that did not evaluate go once the next round completes, but
/// never the last completed one: a server killed after such a round resumes from it.
#[tokio::test]
async fn keeping_only_evaluated_models_resumes_from_the_last_round() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("num-server-rounds=5 eval-every=2 keep-models=evaluated");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let dir = run_dir.path().to_owned();
    let rounds = || -> Vec<u64> {
        numbered_dirs(&dir.join(MODELS_DIR), "round_").unwrap().into_iter().map(|(round, _)| round).collect()
    };

    let handle = start(cfg, run_dir).await;
    let clients: Vec<_> = (0..3).map(|shard| spawn_client(&handle, shard, Some(4))).collect();
    wait_status(&handle, |s| s.completed_rounds == 3).await;
    handle.kill().await;
    for (task, _) in &clients {
        task.abort();
    }
    assert_eq!(rounds(), [0, 2, 3], "round 1 went once round 2 completed; round 3, the last, stays");

    let (run_dir, cfg) = RunDir::open(&dir).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let clients: Vec<_> = (0..3).map(|shard| spawn_client(&handle, shard, None)).collect();
    assert_eq!(handle.finish().await.unwrap().completed_rounds, 5);
    for (task, _) in clients {
        task.await.unwrap().unwrap();
    }
    assert_eq!(rounds(), [0, 2, 4, 5], "round 3 went once round 4 completed");
    let last = read_metrics(&dir).unwrap().pop().unwrap();
    assert_eq!((last.round, last.model_crc32), (5, run_dir.load_model(5).unwrap().checksum()));
}

/// A strategy with state (FedAdam's moments, FedAvgM's velocity, SCAFFOLD's control variates, the server's and
/// each client's, DP-FedAvg's round count, which seeds its noise, and adaptive clipping norm) killed during round 2 of 3 and resumed ends on the model of an uninterrupted run: its
/// state is saved with each round and taken up again on resume.
#[tokio::test]
async fn a_stateful_strategy_resumed_equals_the_uninterrupted_run() {
    for strategy in [
        "fedadam server-lr=0.05",
        "fedavgm server-lr=1 server-momentum=0.5",
        "scaffold",
        "fedavg dp-noise-multiplier=0.1 dp-clip-norm=0.5 dp-clip-quantile=0.5 dp-clip-count-stddev=1",
    ] {
        let cfg = config(&format!("num-server-rounds=3 strategy={strategy}"));
        let uninterrupted = {
            let base = tempfile::tempdir().unwrap();
            let run_dir = RunDir::create(base.path(), &cfg).unwrap();
            let handle = start(cfg.clone(), run_dir.clone()).await;
            let clients: Vec<_> = (0..3).map(|shard| spawn_client(&handle, shard, None)).collect();
            assert_eq!(handle.finish().await.unwrap().completed_rounds, 3);
            for (task, _) in clients {
                task.await.unwrap().unwrap();
            }
            run_dir.load_model(3).unwrap()
        };

        let base = tempfile::tempdir().unwrap();
        let run_dir = RunDir::create(base.path(), &cfg).unwrap();
        let dir = run_dir.path().to_owned();
        let handle = start(cfg.clone(), run_dir).await;
        let clients: Vec<_> = (0..3).map(|shard| spawn_client(&handle, shard, Some(2))).collect();
        wait_status(&handle, |s| s.completed_rounds == 1).await;
        handle.kill().await;
        for (task, _) in &clients {
            task.abort();
        }
        let (run_dir, cfg) = RunDir::open(&dir).unwrap();
        let handle = start(cfg, run_dir.clone()).await;
        let clients: Vec<_> = (0..3).map(|shard| spawn_client(&handle, shard, None)).collect();
        assert_eq!(handle.finish().await.unwrap().completed_rounds, 3);
        for (task, _) in clients {
            task.await.unwrap().unwrap();
        }
        assert_close(&run_dir.load_model(3).unwrap(), &uninterrupted, 1e-6);
    }
}
