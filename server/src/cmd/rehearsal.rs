//! `fedvla rehearsal-inputs`: what a full-size rehearsal runs on, written without a download (see
//! `fedvla_server::rehearsal`): `OUT/policy`, a `smolvla_base`-shaped checkpoint of seeded random bf16 weights with a
//! given backbone folder's tokenizer, and `OUT/data`, a small procedural SO-100 dataset.

use std::path::PathBuf;

use fedvla_server::rehearsal::{write_checkpoint, write_dataset};

#[derive(clap::Args)]
pub struct Args {
    /// Output directory (policy/ and data/ are written into it).
    #[arg(long)]
    out: PathBuf,
    /// Seed of the random weights.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Backbone folder whose tokenizer.json and tokenizer_config.json the checkpoint carries.
    #[arg(long, default_value = "../shared/fixtures/smolvla-tiny-a/vlm")]
    tokenizer: PathBuf,
    /// Episodes of the dataset, and frames per episode.
    #[arg(long, default_value_t = 8)]
    episodes: usize,
    #[arg(long, default_value_t = 4)]
    frames: usize,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let (policy, data) = (args.out.join("policy"), args.out.join("data"));
    write_checkpoint(&policy, args.seed, &args.tokenizer)?;
    println!("wrote {} (smolvla_base's tensors, seeded random bf16 weights, seed {})", policy.display(), args.seed);
    write_dataset(&data, args.episodes, args.frames)?;
    println!("wrote {} ({} episodes of {} frames)", data.display(), args.episodes, args.frames);
    Ok(())
}
