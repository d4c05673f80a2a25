//! `fedvla train`: the centralized baseline of a federation. Same configuration, model, trainer, learning rate,
//! held-out sets and sim evaluation as `simulate`, but one trainer on the union of the clients' training
//! episodes, for as many samples as the federation consumes (rounds x sampled clients x local steps x batch),
//! evaluated at the same sample counts. It writes the same `outputs/<run>/` layout, a "round" being the samples
//! of one federated round, so everything that reads a federation's outputs reads this too.

use std::path::Path;
use std::time::Instant;

use fedvla_federation::{LocalTrainer, NamedTensors, RoundTask, StrategyParams};
use fedvla_learner::trainer::StepProgress;
use fedvla_server::config::WorkloadKind;
use fedvla_server::run_dir::{ModelExporter, RunDir, TrainableSafetensors};
use fedvla_server::smolvla_workload::SmolVlaWorkload;
use fedvla_server::workload::Workload;
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;
use tracing_subscriber::filter::LevelFilter;

use super::ConfigArgs;

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    config: ConfigArgs,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let config = args.config.load()?;
    anyhow::ensure!(config.workload == WorkloadKind::Smolvla, "fedvla train trains the smolvla workload only");
    let run_dir = RunDir::create(Path::new(&config.output_dir), &config)?;
    super::init_tracing(Some(run_dir.log_file()?), LevelFilter::WARN);
    println!("run directory: {}", run_dir.path().display());
    let workload = SmolVlaWorkload::prepare_centralized(&config, &run_dir.path().join(super::SHARDS_DIR))?;
    let mut trainer = workload.centralized_trainer().map_err(super::boxed)?;
    let mut evaluator = workload.evaluator().map_err(super::boxed)?;
    let mut exporters: Vec<Box<dyn ModelExporter>> = vec![Box::new(TrainableSafetensors)];
    exporters.extend(workload.exporters());

    let clients = config.sampled_clients(config.num_clients);
    let steps_per_round = clients as u32 * config.local_steps;
    let rounds = config.num_server_rounds;
    println!(
        "centralized: {rounds} rounds x {clients} clients x {} local steps x batch {} = {} samples",
        config.local_steps,
        config.batch_size,
        rounds * u64::from(steps_per_round) * u64::from(config.batch_size)
    );
    let bar = ProgressBar::new(rounds * u64::from(steps_per_round));
    bar.set_style(ProgressStyle::with_template("[{bar:30}] {pos}/{len} steps {msg} ({elapsed}, eta {eta})")?);

    let mut global = workload.initial_model().map_err(super::boxed)?;
    // Every round's model is saved, as a federation saves it; evaluated rounds get their figures.
    let mut persist =
        |round: u64, global: &NamedTensors, evaluate: bool, mut line: serde_json::Value| -> anyhow::Result<()> {
            let mut metrics = match evaluate {
                true => evaluator.evaluate(global).map_err(super::boxed)?,
                false => Default::default(),
            };
            metrics.extend(run_dir.save_model(round, global, &exporters, &config)?);
            line["round"] = json!(round);
            line["model_version"] = json!(round);
            line["global"] = if metrics.is_empty() { serde_json::Value::Null } else { json!(metrics) };
            line["timestamp"] = json!(chrono::Local::now().to_rfc3339());
            run_dir.append_metrics(&line)?;
            if evaluate {
                bar.println(format!(
                    "round {round}: held-out loss {:.4}, sim success {:?}",
                    metrics.get("heldout_loss").copied().unwrap_or(f64::NAN),
                    metrics.get("success_rate")
                ));
            }
            Ok(())
        };
    persist(0, &global, true, json!({ "clients": [] }))?;
    trainer.set_global(&global).map_err(super::boxed)?;
    let runtime = super::runtime()?;
    for round in 1..=rounds {
        let started = Instant::now();
        let task = RoundTask {
            round,
            model_version: round - 1,
            local_steps: steps_per_round,
            batch_size: config.batch_size,
            lr: config.lr,
            seed: config.seed ^ round.wrapping_mul(0x9e37_79b9_7f4a_7c15),
            strategy: StrategyParams { name: "centralized".into(), proximal_mu: 0.0 },
            deadline_ms: config.round_deadline_ms,
            eval_request: false,
            rollout: None,
        };
        // The optimizer's moments carry over from round to round: one continuous run.
        let before = bar.position();
        let out = runtime
            .block_on(trainer.train_with(&task, async |p: StepProgress| {
                bar.set_position(before + u64::from(p.step));
                bar.set_message(format!("round {round}, loss {:.4}", p.loss));
            }))
            .map_err(super::boxed)?;
        global = out.update;
        let line = json!({
            "seconds": started.elapsed().as_secs_f64(),
            "train_loss": out.train_loss,
            "samples": round * u64::from(steps_per_round) * u64::from(config.batch_size),
            "clients": [],
        });
        persist(round, &global, round.is_multiple_of(config.eval_every) || round == rounds, line)?;
    }
    bar.finish();
    println!("metrics in {}", run_dir.path().join(fedvla_server::run_dir::METRICS_FILE).display());
    Ok(())
}
