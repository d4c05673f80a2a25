//! Writes a small synthetic SO-100 dataset, e.g. to check it with LeRobot:
//! `cargo run -p fedvla-data --example write_synthetic -- OUT_DIR [episodes] [frames] [size]`

use fedvla_data::{CameraSpec, DatasetSpec, DatasetWriter, synthetic};

const TASKS: [&str; 2] = ["put the cube in the bowl", "push the cube to the left"];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let out = args.first().ok_or("usage: write_synthetic OUT_DIR [episodes] [frames] [size]")?;
    let arg = |i: usize, default: usize| args.get(i).map_or(Ok(default), |s| s.parse::<usize>());
    let (episodes, frames, size) = (arg(1, 3)?, arg(2, 20)?, arg(3, 64)? as u32);
    let cameras = vec![CameraSpec::new("top", size, size), CameraSpec::new("wrist", size, size)];
    let mut writer = DatasetWriter::create(out, DatasetSpec::so100(cameras.clone()))?;
    for e in 0..episodes {
        writer.add_episode(&synthetic::episode(e, frames, &cameras, TASKS[e % TASKS.len()]))?;
    }
    let written = writer.finish()?;
    println!("wrote {} episodes, {} frames, {} tasks to {}", written.total_episodes, written.total_frames, written.total_tasks, out);
    Ok(())
}
