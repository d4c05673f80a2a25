//! `fedvla bench`: what a client-round costs on the wire and in the codec, measured from the codec itself.
//! For each model size (LeRobot's default freezing: the action expert and its projections train), the exact
//! bytes of one update under every encoding, frames included, and of a volunteer's download of the global model
//! (whole, or as the round's delta in the encoding, `fedvla_federation::codec::encode_model_delta`); then, at one
//! size, how fast the client encodes
//! and the server decodes a delta of random values; then, per size, training samples/s on the CPU with and
//! without the frozen-feature cache (each row's context keys and values computed once, then reused); then, at one
//! size, how fast FedAvg folds updates (GB/s of f32 updates) and a real server's resident memory over a round of
//! simulated clients ([`fedvla_server::aggregation_memory`]).

use std::time::Instant;

use burn::tensor::Device;
use fedvla_federation::codec::{
    DEFAULT_MAX_FRAME_BYTES, HEADER_LEN, decode_payload, encode_delta_payload, model_deltas_len, payload_len,
};
use fedvla_federation::{FedAvg, NamedTensors, Strategy, TensorSpec, UpdateEncoding};
use fedvla_policy::vlm_with_expert::ContextKv;
use fedvla_policy::weights::init_random;
use fedvla_policy::{Batch, SmolVlaConfig, Trainer};
use fedvla_server::aggregation_memory::{measure_round, model_of_size};

/// What the Python/Flower peer ships per transfer (NOTES.md): the yardstick of the ratios.
const PEER_BYTES: f64 = 1.8e9;

#[derive(clap::Args)]
pub struct Args {
    /// Model sizes to tabulate.
    #[arg(long, value_delimiter = ',', default_value = "tiny,small,base")]
    sizes: Vec<String>,
    /// Size whose codec throughput is timed ("" skips the timing).
    #[arg(long, default_value = "small")]
    time_size: String,
    /// Top-k's fraction.
    #[arg(long, default_value_t = 0.01)]
    topk_fraction: f64,
    /// Clients a round whose top-k updates make a top-k run's global change (FedAvg's holds at most their union of
    /// values), for its download's delta.
    #[arg(long, default_value_t = 3)]
    topk_clients: usize,
    /// Model sizes whose training step is timed with and without the frozen-feature cache ("" skips it; `base`
    /// takes minutes a step on two cores).
    #[arg(long, value_delimiter = ',', default_value = "tiny,small")]
    cache_sizes: Vec<String>,
    /// Samples per step, and timed steps each way, of the cache comparison.
    #[arg(long, default_value_t = 8)]
    cache_batch: usize,
    #[arg(long, default_value_t = 3)]
    cache_steps: usize,
    /// Model size (every tensor) whose aggregation is measured ("" skips it).
    #[arg(long, default_value = "small")]
    aggregation_size: String,
    /// Simulated clients of the measured round, and updates folded for the throughput.
    #[arg(long, default_value_t = 50)]
    aggregation_clients: usize,
}

fn encodings(topk_fraction: f64) -> [UpdateEncoding; 5] {
    [
        UpdateEncoding::F32,
        UpdateEncoding::F16,
        UpdateEncoding::Bf16,
        UpdateEncoding::Int8,
        UpdateEncoding::Topk { fraction: topk_fraction },
    ]
}

/// The trainable tensors' names and shapes under LeRobot's defaults.
fn trainable_spec(size: &str) -> anyhow::Result<TensorSpec> {
    let cfg = SmolVlaConfig::preset(size)?;
    Ok(cfg.param_specs().into_iter().filter(|p| p.trainable).map(|p| (p.name, p.shape)).collect())
}

/// One update's bytes on the wire: its payload and a header per frame.
fn wire_bytes(spec: &TensorSpec, encoding: UpdateEncoding) -> usize {
    let payload = payload_len(spec, encoding);
    payload + payload.div_ceil(DEFAULT_MAX_FRAME_BYTES - HEADER_LEN) * HEADER_LEN
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let encodings = encodings(args.topk_fraction);
    println!("Upload per client-round (one update, {} B frames), LeRobot's default freezing:", DEFAULT_MAX_FRAME_BYTES);
    println!("| size | trainable values | encoding | bytes | MB | of f32 | peer's 1.8 GB / this |");
    println!("|---|---|---|---|---|---|---|");
    for size in &args.sizes {
        let spec = trainable_spec(size)?;
        let values = spec.byte_size() / 4;
        let f32_bytes = wire_bytes(&spec, UpdateEncoding::F32) as f64;
        for encoding in encodings {
            let bytes = wire_bytes(&spec, encoding);
            let name = match encoding {
                UpdateEncoding::Topk { fraction } => format!("topk {}%", fraction * 100.0),
                other => other.name().to_owned(),
            };
            println!(
                "| {size} | {values} | {name} | {bytes} | {:.2} | {:.3} | {:.0}x |",
                bytes as f64 / 1e6,
                bytes as f64 / f32_bytes,
                PEER_BYTES / bytes as f64
            );
        }
    }
    download_table(&args.sizes, &encodings, args.topk_clients)?;
    if !args.time_size.is_empty() {
        codec_speed(&args.time_size, &encodings)?;
    }
    let sizes: Vec<&String> = args.cache_sizes.iter().filter(|s| !s.is_empty()).collect();
    if !sizes.is_empty() {
        println!(
            "\nTraining on the CPU, LeRobot's default freezing, batch {}, {} steps each way after one untimed:",
            args.cache_batch, args.cache_steps
        );
        println!("| size | without the cache, samples/s | with it, samples/s | ratio | cache per sample |");
        println!("|---|---|---|---|---|");
    }
    for size in sizes {
        cache_speed(size, args.cache_batch, args.cache_steps)?;
    }
    if !args.aggregation_size.is_empty() {
        aggregation(&args.aggregation_size, args.aggregation_clients)?;
    }
    Ok(())
}

/// A volunteer's download of the global model per round: the whole model (f32 safetensors, what f32 runs and a
/// volunteer holding no earlier version get), or, holding the last version, the round's delta as one chain. Top-k's
/// delta holds every nonzero value of FedAvg's change, at most the union of `topk_clients` clients' top-k values.
fn download_table(sizes: &[String], encodings: &[UpdateEncoding], topk_clients: usize) -> anyhow::Result<()> {
    println!(
        "\nThe frozen tensors, downloaded once, in the checkpoint's dtype (tensor data, without the safetensors header):"
    );
    println!("| size | frozen values | f32 (random init) | bf16 (`smolvla_base`) |");
    println!("|---|---|---|---|");
    for size in sizes {
        let cfg = SmolVlaConfig::preset(size)?;
        let frozen: usize =
            cfg.param_specs().iter().filter(|p| !p.trainable).map(fedvla_policy::ParamSpec::numel).sum();
        println!("| {size} | {frozen} | {:.1} MB | {:.1} MB |", 4.0 * frozen as f64 / 1e6, 2.0 * frozen as f64 / 1e6);
    }
    println!("\nDownload per client-round of a volunteer that holds the last version, LeRobot's default freezing:");
    println!("| size | whole model | encoding | bytes | MB | of the whole model |");
    println!("|---|---|---|---|---|---|");
    for size in sizes {
        let spec = trainable_spec(size)?;
        let mut zeros = NamedTensors::new();
        for (name, shape) in spec.iter() {
            zeros.insert(name, shape.to_vec(), vec![0.0; shape.iter().product()])?;
        }
        let whole = zeros.to_safetensors()?.len();
        drop(zeros);
        for &encoding in encodings.iter().filter(|e| **e != UpdateEncoding::F32) {
            let (name, payload) = match encoding {
                UpdateEncoding::Topk { fraction } => {
                    let union = (fraction * topk_clients as f64).min(1.0);
                    let payload = payload_len(&spec, UpdateEncoding::Topk { fraction: union });
                    (format!("topk {}%, {topk_clients} clients (at most)", fraction * 100.0), payload)
                }
                other => (other.name().to_owned(), payload_len(&spec, other)),
            };
            let bytes = model_deltas_len(1, payload);
            println!(
                "| {size} | {whole} | {name} | {bytes} | {:.2} | {:.3} |",
                bytes as f64 / 1e6,
                bytes as f64 / whole as f64
            );
        }
    }
    Ok(())
}

/// FedAvg's fold throughput over `clients` updates of every tensor of `size`, one thread, and a real server's
/// resident memory over a round of `clients` simulated volunteers.
fn aggregation(size: &str, clients: usize) -> anyhow::Result<()> {
    let global = model_of_size(size, 0)?;
    let updates: Vec<NamedTensors> = (0..clients.min(8))
        .map(|i| global.zip_map(&global, |g, _| g + (i as f32 + 1.0) * 1e-4))
        .collect::<Result<_, _>>()?;
    let mut round = FedAvg.begin(&global);
    let start = Instant::now();
    for i in 0..clients {
        round.fold((&updates[i % updates.len()], 100 + i as u64).into())?;
    }
    let fold = start.elapsed().as_secs_f64();
    round.finish()?;
    let model_bytes = 4 * global.iter().map(|(_, t)| t.values.len()).sum::<usize>();
    let gb = (clients * model_bytes) as f64 / 1e9;
    let output = std::env::temp_dir().join(format!("fedvla-bench-aggregation-{}", std::process::id()));
    let r = measure_round(&std::env::current_exe()?, size, clients, &output)?;
    std::fs::remove_dir_all(&output)?;
    let mb = |b: u64| b as f64 / 1e6;
    println!(
        "\nAggregation of `{size}` (every tensor, {:.1} MB of f32), FedAvg, {clients} clients:",
        mb(model_bytes as u64)
    );
    println!("| fold, one thread | server RSS before the round | peak over it | growth | round |");
    println!("|---|---|---|---|---|");
    println!(
        "| {:.2} GB/s | {:.0} MB | {:.0} MB | {:.1} MB ({:.1} models) | {:.1} s |",
        gb / fold,
        mb(r.before_rss_bytes),
        mb(r.peak_rss_bytes),
        mb(r.peak_rss_bytes.saturating_sub(r.before_rss_bytes)),
        r.growth_in_models(),
        r.round_seconds
    );
    Ok(())
}

/// How fast the client encodes and the server decodes a random delta of `size`'s trainable tensors.
fn codec_speed(size: &str, encodings: &[UpdateEncoding]) -> anyhow::Result<()> {
    let spec = trainable_spec(size)?;
    let mut delta = NamedTensors::new();
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    for (name, shape) in spec.iter() {
        let values = (0..shape.iter().product::<usize>())
            .map(|_| {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((state >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 1e-3
            })
            .collect();
        delta.insert(name, shape.to_vec(), values)?;
    }
    let mb = spec.byte_size() as f64 / 1e6;
    println!("\nCodec throughput at {} ({mb:.1} MB of f32 delta), one thread:", size);
    println!("| encoding | encode MB/s | decode MB/s |");
    println!("|---|---|---|");
    for &encoding in encodings.iter().filter(|e| **e != UpdateEncoding::F32) {
        let mut residual = delta.clone();
        let start = Instant::now();
        let payload = encode_delta_payload(&mut residual, encoding);
        let encode = start.elapsed().as_secs_f64();
        let start = Instant::now();
        decode_payload(&payload, &spec, encoding)?;
        let decode = start.elapsed().as_secs_f64();
        println!("| {} | {:.0} | {:.0} |", encoding.name(), mb / encode, mb / decode);
    }
    Ok(())
}

/// One row of the cache table: training samples/s of `size` computing every step's context, and reusing each
/// sample's (computed before the timed steps, as a cache holds them from a row's second visit on).
fn cache_speed(size: &str, batch_size: usize, steps: usize) -> anyhow::Result<()> {
    let cfg = SmolVlaConfig::preset(size)?;
    anyhow::ensure!(cfg.backbone_frozen(), "model size {size} trains its backbone: nothing to cache");
    let weights = init_random(&cfg.param_specs(), 1);
    let batch = Batch::random(&cfg, batch_size, 7);
    let mut trainer = Trainer::new(&cfg, &weights, &Device::flex().autodiff(), 3)?;
    let time = |trainer: &mut Trainer, context: Option<&ContextKv>| -> anyhow::Result<f64> {
        trainer.train_step_from(&batch, context, 1e-4)?;
        let start = Instant::now();
        for _ in 0..steps {
            trainer.train_step_from(&batch, context, 1e-4)?;
        }
        Ok((steps * batch_size) as f64 / start.elapsed().as_secs_f64())
    };
    let without = time(&mut trainer, None)?;
    let rows: Vec<ContextKv> =
        (0..batch_size).map(|n| trainer.context_kv(&batch.rows(&[n]))).collect::<Result<_, _>>()?;
    let context = ContextKv::stack(&rows.iter().collect::<Vec<_>>());
    let with = time(&mut trainer, Some(&context))?;
    println!(
        "| {size} | {without:.2} | {with:.2} | {:.1}x | {:.2} MB |",
        with / without,
        rows.iter().map(ContextKv::bytes).sum::<usize>() as f64 / batch_size as f64 / 1e6
    );
    Ok(())
}
