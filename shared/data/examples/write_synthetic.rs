//! Writes a small synthetic SO-100 dataset, e.g. to check it with LeRobot:
//! `cargo run -p fedvla-data --example write_synthetic -- OUT_DIR [episodes] [frames] [height] [width] [--small-files]`
//! (`--small-files` lowers the rollover sizes to 1 MB so that larger runs spread over several files).

use fedvla_data::{CameraSpec, DatasetSpec, DatasetWriter, synthetic};

const TASKS: [&str; 2] = ["put the cube in the bowl", "push the cube to the left"];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let all_args: Vec<String> = std::env::args().skip(1).collect();
    let small_files = all_args.iter().any(|a| a == "--small-files");
    let args: Vec<&String> = all_args.iter().filter(|a| !a.starts_with("--")).collect();
    let out =
        args.first().ok_or("usage: write_synthetic OUT_DIR [episodes] [frames] [height] [width] [--small-files]")?;
    let arg = |i: usize, default: usize| args.get(i).map_or(Ok(default), |s| s.parse::<usize>());
    let (episodes, frames, height) = (arg(1, 3)?, arg(2, 20)?, arg(3, 64)? as u32);
    let width = arg(4, height as usize)? as u32;
    let cameras = vec![CameraSpec::new("top", height, width), CameraSpec::new("wrist", height, width)];
    let mut spec = DatasetSpec::so100(cameras.clone());
    if small_files {
        spec.data_files_size_in_mb = 1;
        spec.video_files_size_in_mb = 1;
    }
    let started = std::time::Instant::now();
    let mut writer = DatasetWriter::create(out, spec)?;
    for e in 0..episodes {
        writer.add_episode(&synthetic::episode(e, frames, &cameras, TASKS[e % TASKS.len()]))?;
    }
    let written = writer.finish()?;
    println!(
        "wrote {} episodes, {} frames, {} tasks to {} in {:.2}s",
        written.total_episodes,
        written.total_frames,
        written.total_tasks,
        out,
        started.elapsed().as_secs_f64()
    );
    Ok(())
}
