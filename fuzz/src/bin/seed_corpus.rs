//! Writes each target's seed inputs to `fuzz/corpus/<target>/seed-<n>` (run from the repository root:
//! `cargo +nightly run --manifest-path fuzz/Cargo.toml --bin seed_corpus`).

fn main() -> std::io::Result<()> {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("corpus");
    for target in ["protocol_json", "update_codec", "reassembly"] {
        let dir = root.join(target);
        std::fs::create_dir_all(&dir)?;
        let seeds = fedvla_fuzz::seeds(target);
        for (i, seed) in seeds.iter().enumerate() {
            std::fs::write(dir.join(format!("seed-{i}")), seed)?;
        }
        println!("{target}: {} seeds in {}", seeds.len(), dir.display());
    }
    Ok(())
}
