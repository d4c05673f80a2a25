//! The run directory's rollouts as the console shows them: each round's videos and `results.json`, the global
//! model's (`global_model/round_N/rollouts/`) and each client's (`evaluate/round_N/client_K/`), and the rounds
//! whose LeRobot policy can be downloaded.

use std::collections::BTreeMap;
use std::path::Path;

use fedvla_aggregator::records::RolloutResults;
use fedvla_aggregator::run_dir::{EVALUATE_DIR, MODELS_DIR, POLICY_DIR, RESULTS_FILE, ROLLOUTS_DIR, numbered_dirs};
use percent_encoding::{AsciiSet, NON_ALPHANUMERIC, utf8_percent_encode};
use serde::Serialize;

/// Videos and results of one round: the global model's sim rollouts and each client's.
#[derive(Debug, Default, Serialize)]
pub struct RoundGallery {
    round: u64,
    global: Option<VideoSet>,
    clients: Vec<ClientVideos>,
}

#[derive(Debug, Serialize)]
struct ClientVideos {
    client_id: u64,
    #[serde(flatten)]
    set: VideoSet,
}

#[derive(Debug, Serialize)]
struct VideoSet {
    /// Console URLs (`/console/api/file/...`; the page adds its token).
    videos: Vec<String>,
    /// The directory's results.json, when there is one that parses.
    results: Option<RolloutResults>,
}

/// `global_model/round_N/rollouts/` and `evaluate/round_N/client_K/`, by round; rounds without either are left out.
pub fn gallery(run_dir: &Path) -> std::io::Result<Vec<RoundGallery>> {
    let mut rounds: BTreeMap<u64, RoundGallery> = BTreeMap::new();
    for (round, dir) in numbered_dirs(&run_dir.join(MODELS_DIR), "round_")? {
        if let Some(set) = video_set(run_dir, &dir.join(ROLLOUTS_DIR))? {
            rounds.entry(round).or_insert_with(|| RoundGallery { round, ..RoundGallery::default() }).global = Some(set);
        }
    }
    for (round, round_dir) in numbered_dirs(&run_dir.join(EVALUATE_DIR), "round_")? {
        for (client_id, dir) in numbered_dirs(&round_dir, "client_")? {
            if let Some(set) = video_set(run_dir, &dir)? {
                let entry = rounds.entry(round).or_insert_with(|| RoundGallery { round, ..RoundGallery::default() });
                entry.clients.push(ClientVideos { client_id, set });
            }
        }
    }
    Ok(rounds.into_values().collect())
}

/// Rounds whose LeRobot policy directory can be downloaded.
pub fn checkpoint_rounds(run_dir: &Path) -> std::io::Result<Vec<u64>> {
    Ok(numbered_dirs(&run_dir.join(MODELS_DIR), "round_")?
        .into_iter()
        .filter(|(_, dir)| dir.join(POLICY_DIR).is_dir())
        .map(|(round, _)| round)
        .collect())
}

/// The videos (`.mp4`, `.webm`) and results.json in `dir`, if it holds either.
fn video_set(run_dir: &Path, dir: &Path) -> std::io::Result<Option<VideoSet>> {
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e),
    };
    let mut names = Vec::new();
    for entry in entries {
        let name = entry?.file_name().to_string_lossy().into_owned();
        if name.ends_with(".mp4") || name.ends_with(".webm") {
            names.push(name);
        }
    }
    // episode_2 before episode_10.
    names.sort_by(|a, b| (a.len(), a).cmp(&(b.len(), b)));
    let results = match std::fs::read(dir.join(RESULTS_FILE)) {
        Ok(bytes) => serde_json::from_slice(&bytes).ok(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(e) => return Err(e),
    };
    if names.is_empty() && results.is_none() {
        return Ok(None);
    }
    let relative = dir.strip_prefix(run_dir).expect("gallery directories are inside the run directory");
    let videos = names.iter().map(|name| file_url(&relative.join(name))).collect();
    Ok(Some(VideoSet { videos, results }))
}

/// Characters a URL path segment may not carry as they are.
const SEGMENT: &AsciiSet = &NON_ALPHANUMERIC.remove(b'-').remove(b'.').remove(b'_').remove(b'~');

/// The console URL of a file in the run directory.
fn file_url(relative: &Path) -> String {
    let segments: Vec<String> = relative
        .components()
        .map(|c| utf8_percent_encode(&c.as_os_str().to_string_lossy(), SEGMENT).to_string())
        .collect();
    format!("/console/api/file/{}", segments.join("/"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gallery_lists_rounds_in_order_with_urls() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path();
        let rollouts = run.join("global_model/round_2/rollouts");
        std::fs::create_dir_all(&rollouts).unwrap();
        for name in ["episode_10.mp4", "episode_2.mp4"] {
            std::fs::write(rollouts.join(name), b"x").unwrap();
        }
        std::fs::write(rollouts.join(RESULTS_FILE), br#"{"success_rate": 0.5}"#).unwrap();
        std::fs::create_dir_all(run.join("global_model/round_3.tmp/rollouts")).unwrap();
        std::fs::create_dir_all(run.join("global_model/round_1/policy")).unwrap();
        let client = run.join("evaluate/round_2/client_7");
        std::fs::create_dir_all(&client).unwrap();
        std::fs::write(client.join("a b.webm"), b"x").unwrap();

        let rounds = gallery(run).unwrap();
        assert_eq!(rounds.len(), 1, "round 1 has no videos, round_3.tmp is not a round");
        let round = &rounds[0];
        assert_eq!(round.round, 2);
        let global = round.global.as_ref().unwrap();
        assert_eq!(
            global.videos,
            [
                "/console/api/file/global_model/round_2/rollouts/episode_2.mp4",
                "/console/api/file/global_model/round_2/rollouts/episode_10.mp4"
            ]
        );
        assert_eq!(global.results.as_ref().unwrap().success_rate, Some(0.5));
        assert_eq!(round.clients[0].client_id, 7);
        assert_eq!(round.clients[0].set.videos, ["/console/api/file/evaluate/round_2/client_7/a%20b.webm"]);
        assert_eq!(checkpoint_rounds(run).unwrap(), [1]);
    }
}
