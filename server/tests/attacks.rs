//! One attacker among five clients (seven for Bulyan), sampled every round, sending its update scaled by 100 (and, separately,
//! sign-flipped): FedAvg is broken by it, while the robust rules stay where they are without the attacker.
//! On the linreg workload, over loopback, through `simulate`'s own client spawning. The rules are judged alone
//! (`update-norm-factor=0`), but for the test of the server's own norm screen, which runs before any rule.

use fedvla_aggregator::config::RunConfig;
use fedvla_aggregator::records::{MetricsLine, read_metrics};
use fedvla_aggregator::run_dir::RunDir;
use fedvla_server::runs::{Bars, federated};

/// The metrics of a 3-round, 5-client linreg federation.
fn federation(overrides: &str) -> Vec<MetricsLine> {
    let tmp = tempfile::tempdir().unwrap();
    let config = RunConfig::default()
        .with_overrides(&format!(
            "workload=linreg num-clients=5 min-clients=5 min-fit=5 fraction-fit=1.0 num-server-rounds=3 eval-every=1 \
             local-steps=30 batch-size=8 lr=0.05 round-deadline-ms=20000 {overrides}"
        ))
        .unwrap();
    let run_dir = RunDir::create(tmp.path(), &config).unwrap();
    federated(config, run_dir.clone(), &Bars::hidden()).unwrap();
    read_metrics(run_dir.path()).unwrap()
}

fn last_loss(lines: &[MetricsLine]) -> f64 {
    lines.last().and_then(|l| l.global.as_ref()).and_then(|g| g.eval.as_ref()).expect("evaluated").heldout_loss
}

/// The final server held-out loss of the federation, its strategy judging the updates alone.
fn final_loss(overrides: &str) -> f64 {
    last_loss(&federation(&format!("update-norm-factor=0 {overrides}")))
}

/// The server's norm screen (on by default) leaves an attacker scaling its change by 100, or flipping it and scaling
/// by 10, out of every round, before FedAvg sees it: the run ends where the four honest clients alone take it, and
/// every refusal is on record.
#[test]
fn the_norm_screen_leaves_a_scaled_or_flipped_update_out_before_fedavg_sees_it() {
    let four = "strategy=fedavg min-fit=4";
    let clean = final_loss(four);
    // At the default factor (3) a change sent 10x larger is out whichever way it points.
    for attack in ["attack=scale attack-strength=100", "attack=sign-flip attack-strength=10"] {
        let screened = federation(&format!("{four} attackers=1 {attack}"));
        let loss = last_loss(&screened);
        assert!((loss - clean).abs() < 0.5 * clean, "{attack}: {loss} against {clean}");
        for line in &screened[1..] {
            assert_eq!(line.rejections.get("update_norm_outlier"), Some(&1), "{attack}, round {}", line.round);
            let dropped: Vec<_> = line.clients.iter().filter(|c| !c.accepted).collect();
            assert_eq!(dropped.len(), 1, "{attack}, round {}", line.round);
            assert!(dropped[0].dropped.as_deref().is_some_and(|r| r.contains("median norm")), "{:?}", dropped[0]);
        }
    }
    // Honest clients are never screened out.
    let honest = federation(four);
    assert!(honest.iter().all(|l| l.rejections.is_empty() && l.clients.iter().all(|c| c.accepted)));
}

#[test]
fn fedavg_breaks_under_one_attacker_and_the_robust_rules_do_not() {
    for attack in
        ["attack=scale attack-strength=100", "attack=sign-flip attack-strength=10", "attack=noise attack-strength=10"]
    {
        let clean = final_loss("strategy=fedavg");
        let broken = final_loss(&format!("strategy=fedavg attackers=1 {attack}"));
        println!("fedavg, {attack}: held-out loss {clean:.5} without the attacker, {broken:.5} with");
        assert!(broken > 10.0 * clean, "{attack}: FedAvg's loss {clean} -> {broken} under attack");
        let rules = [
            "strategy=median",
            "strategy=trimmed-mean",
            "strategy=krum",
            "strategy=multi-krum krum-keep=3",
            // Bulyan needs 4f + 3 = 7 clients for its one attacker.
            "strategy=bulyan num-clients=7 min-clients=7 min-fit=7",
        ];
        for rule in rules {
            let without = final_loss(rule);
            let with = final_loss(&format!("{rule} attackers=1 {attack}"));
            println!("{rule}, {attack}: held-out loss {without:.5} without the attacker, {with:.5} with");
            assert!(
                with <= without * 1.05 + 1e-9,
                "{rule}, {attack}: loss {without} without the attacker, {with} with"
            );
        }
    }
}

/// Data poisoning: two clients of five train on their shards with the targets shuffled among their examples and
/// send what that teaches, updates no norm or sign gives away. FedAvg takes them in (one such client barely moves
/// it: 30 steps on shuffled targets pull the weights toward zero slowly); the coordinate-wise median, which
/// tolerates any minority, holds better.
#[test]
fn label_shuffling_attackers_poison_fedavg_more_than_the_median() {
    let attack = "attackers=2 attack=label-shuffle";
    let clean = final_loss("strategy=fedavg");
    let poisoned = final_loss(&format!("strategy=fedavg {attack}"));
    println!("fedavg, 2 label-shufflers of 5: held-out loss {clean:.5} without them, {poisoned:.5} with");
    assert!(poisoned > 1.5 * clean, "label-shuffle: FedAvg's loss {clean} -> {poisoned}");
    let (without, with) = (final_loss("strategy=median"), final_loss(&format!("strategy=median {attack}")));
    println!("median, 2 label-shufflers of 5: held-out loss {without:.5} without them, {with:.5} with");
    assert!(with < poisoned, "label-shuffle: the median's {with} against FedAvg's {poisoned}");
}
