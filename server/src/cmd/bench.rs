//! `fedvla bench`: what a client-round costs on the wire and in the codec, measured from the codec itself.
//! For each model size (LeRobot's default freezing: the action expert and its projections train), the exact
//! bytes of one update under every encoding, frames included; then, at one size, how fast the client encodes
//! and the server decodes a delta of random values.

use std::time::Instant;

use fedvla_federation::codec::{
    DEFAULT_MAX_FRAME_BYTES, HEADER_LEN, decode_payload, encode_delta_payload, payload_len,
};
use fedvla_federation::{NamedTensors, TensorSpec, UpdateEncoding};
use fedvla_policy::SmolVlaConfig;

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
    if args.time_size.is_empty() {
        return Ok(());
    }
    let spec = trainable_spec(&args.time_size)?;
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
    println!("\nCodec throughput at {} ({mb:.1} MB of f32 delta), one thread:", args.time_size);
    println!("| encoding | encode MB/s | decode MB/s |");
    println!("|---|---|---|");
    for encoding in encodings.into_iter().filter(|e| *e != UpdateEncoding::F32) {
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
