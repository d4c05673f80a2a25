//! Opens a LeRobot dataset (v3.0 or v2.1) and prints its metadata and, per episode and camera, the
//! mean RGB value of the first and last decoded frames (to compare decoders, e.g. with PyAV):
//! `cargo run -p fedvla-data [--features av1] --example inspect_dataset -- DATASET_DIR`

use fedvla_data::LeRobotDataset;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let root = std::env::args().nth(1).ok_or("usage: inspect_dataset DATASET_DIR")?;
    let ds = LeRobotDataset::open(&root)?;
    let info = ds.info();
    println!(
        "{root}: {} ({:?}), {} episodes, {} frames at {} fps, robot {:?}, tasks {:?}",
        info.codebase_version,
        ds.version(),
        ds.episodes().len(),
        ds.len(),
        ds.fps(),
        info.robot_type,
        ds.tasks()
    );
    for episode in ds.episodes() {
        for camera in ds.camera_keys() {
            let ends = [episode.dataset_from_index, episode.dataset_to_index - 1];
            let frames = ds.camera_frames(&camera, episode, &ends)?;
            let means: Vec<String> = frames
                .iter()
                .map(|f| {
                    let mean = f.data.iter().map(|&v| f64::from(v)).sum::<f64>() / f.data.len() as f64;
                    format!("{mean:.3}")
                })
                .collect();
            println!("episode {} {camera}: frames {:?} mean pixel {}", episode.episode_index, ends, means.join(" / "));
        }
    }
    Ok(())
}
