//! `fedvla parity`: recomputes a LeRobot golden fixture with our SmolVLA (CPU, with autodiff for the
//! gradient outputs) and compares tensor by tensor.

use std::path::PathBuf;

use anyhow::Context;
use burn::tensor::Device;

#[derive(clap::Args)]
pub struct Args {
    /// Fixture folder: config.json, vlm/, model.safetensors, inputs.safetensors, outputs.safetensors.
    #[arg(long)]
    fixture: PathBuf,
    /// Largest max-abs difference a tensor may show.
    #[arg(long, default_value_t = 1e-4)]
    tolerance: f64,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let report = fedvla_policy::parity::run(&args.fixture, &Device::flex().autodiff(), args.tolerance)
        .with_context(|| format!("parity check of {}", args.fixture.display()))?;
    let shapes: Vec<String> = report.rows.iter().map(|r| format!("{:?}", r.shape)).collect();
    let name_width = report.rows.iter().map(|r| r.name.len()).max().unwrap_or(0);
    let shape_width = shapes.iter().map(String::len).max().unwrap_or(0);
    let mut failing = Vec::new();
    for (row, shape) in report.rows.iter().zip(&shapes) {
        let diff = match row.max_abs_diff {
            Some(d) => format!("{d:.3e}"),
            None => "-".to_string(),
        };
        let ok = row.max_abs_diff.is_some_and(|d| d <= report.tolerance);
        if !ok {
            failing.push(row.name.as_str());
        }
        println!(
            "{:<name_width$}  {shape:<shape_width$}  {diff:>9}  {}{}",
            row.name,
            if ok { "" } else { "FAIL " },
            row.note
        );
    }
    println!(
        "{} tensors, {} over tolerance or not recomputed; worst max abs diff {:.3e} (tolerance {:e})",
        report.rows.len(),
        failing.len(),
        report.worst(),
        report.tolerance
    );
    anyhow::ensure!(
        !report.rows.is_empty(),
        "{}: the fixture's outputs.safetensors holds no tensors",
        args.fixture.display()
    );
    anyhow::ensure!(
        report.passed(),
        "parity failed for {} of {} tensors: {}",
        failing.len(),
        report.rows.len(),
        failing.join(", ")
    );
    println!("parity passed");
    Ok(())
}
