//! What a client tells the server of the data it trains on, and what the server tells every client back: a
//! dataset's signature (what the server checks an own dataset against before it trains on it), the moments of a
//! client's state and action (count, sums, sums of squares, min and max per feature, never a row), and the run's
//! normalisation statistics, which the server combines exactly from every client's moments when the run agrees
//! them by federated statistics.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// The features whose statistics normalise the policy's inputs and targets.
pub const NORMALISED_FEATURES: [&str; 2] = ["observation.state", "action"];

/// What makes a LeRobot dataset fit a run: a policy trained on one reads the other's frames, states and actions
/// the same way only when all of this agrees.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DatasetSignature {
    pub robot_type: Option<String>,
    pub fps: u32,
    pub state_dim: usize,
    pub state_names: Vec<String>,
    pub action_dim: usize,
    pub action_names: Vec<String>,
    /// Camera feature keys in the dataset's order.
    pub cameras: Vec<String>,
}

impl DatasetSignature {
    /// Every way `self` (a client's dataset) differs from `run` (the run's), in words naming both sides; empty
    /// when they fit.
    pub fn differences(&self, run: &Self) -> Vec<String> {
        let mut out = Vec::new();
        let mut differ = |what: &str, mine: String, theirs: String| {
            if mine != theirs {
                out.push(format!("{what}: this dataset has {mine}, the run's has {theirs}"));
            }
        };
        differ("robot type", format!("{:?}", self.robot_type), format!("{:?}", run.robot_type));
        differ("fps", self.fps.to_string(), run.fps.to_string());
        differ("observation.state dimension", self.state_dim.to_string(), run.state_dim.to_string());
        differ("observation.state names", format!("{:?}", self.state_names), format!("{:?}", run.state_names));
        differ("action dimension", self.action_dim.to_string(), run.action_dim.to_string());
        differ("action names", format!("{:?}", self.action_names), format!("{:?}", run.action_names));
        let (mine, theirs) = (&self.cameras, &run.cameras);
        let missing: Vec<&String> = theirs.iter().filter(|c| !mine.contains(c)).collect();
        let extra: Vec<&String> = mine.iter().filter(|c| !theirs.contains(c)).collect();
        if !missing.is_empty() {
            out.push(format!("cameras: this dataset lacks {missing:?} (the run's cameras are {theirs:?})"));
        }
        if !extra.is_empty() {
            out.push(format!("cameras: this dataset has {extra:?}, which the run's {theirs:?} lack"));
        }
        if missing.is_empty() && extra.is_empty() && mine.len() != theirs.len() {
            out.push(format!("camera count: this dataset has {}, the run's has {}", mine.len(), theirs.len()));
        }
        out
    }

    /// Whether a dataset of this signature fits a run of signature `run`: an error naming every difference.
    pub fn check_fits(&self, run: &Self) -> Result<(), String> {
        match self.differences(run) {
            d if d.is_empty() => Ok(()),
            d => Err(format!("the dataset does not fit this run: {}", d.join("; "))),
        }
    }
}

/// Sufficient statistics of one feature over some rows: enough to combine exactly with others' into the
/// statistics of all their rows together, and nothing that gives a row away.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeatureMoments {
    pub count: u64,
    pub sum: Vec<f64>,
    pub sum_sq: Vec<f64>,
    pub min: Vec<f64>,
    pub max: Vec<f64>,
}

impl FeatureMoments {
    /// The moments of `rows` (each `dim` long).
    pub fn of_rows<'a>(dim: usize, rows: impl IntoIterator<Item = &'a [f32]>) -> Self {
        let mut m = Self {
            count: 0,
            sum: vec![0.0; dim],
            sum_sq: vec![0.0; dim],
            min: vec![f64::INFINITY; dim],
            max: vec![f64::NEG_INFINITY; dim],
        };
        for row in rows {
            m.count += 1;
            for (d, &v) in row.iter().enumerate().take(dim) {
                let v = f64::from(v);
                m.sum[d] += v;
                m.sum_sq[d] += v * v;
                m.min[d] = m.min[d].min(v);
                m.max[d] = m.max[d].max(v);
            }
        }
        m
    }

    fn dim(&self) -> usize {
        self.sum.len()
    }

    /// Whether it is well formed: every vector `dim` long and finite, some rows.
    fn check(&self, feature: &str) -> Result<(), String> {
        let d = self.dim();
        let vectors = [&self.sum_sq, &self.min, &self.max];
        if vectors.iter().any(|v| v.len() != d) {
            return Err(format!("{feature}: sums, sums of squares, min and max differ in length"));
        }
        if self.count == 0 {
            return Err(format!("{feature}: no rows"));
        }
        if [&self.sum, &self.sum_sq, &self.min, &self.max].iter().any(|v| v.iter().any(|x| !x.is_finite())) {
            return Err(format!("{feature}: a moment is not finite"));
        }
        Ok(())
    }
}

/// A client's data, as it tells the server on join.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DataReport {
    /// Present when the client trains on its own dataset rather than a server shard.
    pub own: Option<OwnDataset>,
    /// Moments of [`NORMALISED_FEATURES`] over every row of its data.
    pub moments: BTreeMap<String, FeatureMoments>,
}

/// A dataset a volunteer brings: what the server checks and weighs it by. The example count is a claim: the
/// server cannot see the data.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OwnDataset {
    pub signature: DatasetSignature,
    /// Frames of its training split.
    pub train_examples: u64,
}

/// Normalisation statistics of one feature.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeatureSummary {
    pub count: u64,
    pub mean: Vec<f64>,
    /// Population standard deviation (LeRobot's).
    pub std: Vec<f64>,
    pub min: Vec<f64>,
    pub max: Vec<f64>,
}

/// Where a run's normalisation statistics come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StatsSource {
    /// The run's dataset's `meta/stats.json`.
    Dataset,
    /// Combined from the moments of the clients' data (`federated-stats`).
    Federated,
}

/// The statistics every client, the server's evaluation, its rollouts and its exports normalise with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NormalizationStats {
    pub source: StatsSource,
    /// How many clients' moments were combined (0 for the dataset's).
    pub clients: u32,
    pub features: BTreeMap<String, FeatureSummary>,
}

impl NormalizationStats {
    /// The exact statistics of all the rows behind `reports` together: the pooled count, mean and population
    /// standard deviation, min and max of every feature of [`NORMALISED_FEATURES`]. Refuses reports that lack a
    /// feature, disagree on a dimension or are not finite.
    pub fn combine(reports: &[&DataReport]) -> Result<Self, String> {
        let mut features = BTreeMap::new();
        for feature in NORMALISED_FEATURES {
            let mut parts = Vec::with_capacity(reports.len());
            for (i, report) in reports.iter().enumerate() {
                let m =
                    report.moments.get(feature).ok_or_else(|| format!("client {i} sent no moments of {feature}"))?;
                m.check(feature).map_err(|e| format!("client {i}: {e}"))?;
                parts.push(m);
            }
            let first = parts.first().ok_or("no client data to combine")?;
            let dim = first.dim();
            if let Some(m) = parts.iter().find(|m| m.dim() != dim) {
                return Err(format!("{feature}: dimension {} against {dim}", m.dim()));
            }
            let count: u64 = parts.iter().map(|m| m.count).sum();
            let n = count as f64;
            let column = |d: usize, pick: fn(&FeatureMoments) -> &Vec<f64>| parts.iter().map(move |m| pick(m)[d]);
            let mean: Vec<f64> = (0..dim).map(|d| column(d, |m| &m.sum).sum::<f64>() / n).collect();
            let std = (0..dim)
                .map(|d| (column(d, |m| &m.sum_sq).sum::<f64>() / n - mean[d] * mean[d]).max(0.0).sqrt())
                .collect();
            let min = (0..dim).map(|d| column(d, |m| &m.min).fold(f64::INFINITY, f64::min)).collect();
            let max = (0..dim).map(|d| column(d, |m| &m.max).fold(f64::NEG_INFINITY, f64::max)).collect();
            features.insert(feature.to_owned(), FeatureSummary { count, mean, std, min, max });
        }
        Ok(Self { source: StatsSource::Federated, clients: reports.len() as u32, features })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(rows: &[[f32; 2]]) -> DataReport {
        let moments = FeatureMoments::of_rows(2, rows.iter().map(|r| r.as_slice()));
        let moments = NORMALISED_FEATURES.iter().map(|f| ((*f).to_owned(), moments.clone())).collect();
        DataReport { own: None, moments }
    }

    /// Two clients' moments combine into the statistics of their rows pooled, computed by hand.
    #[test]
    fn moments_combine_into_the_pooled_statistics() {
        let a = report(&[[1.0, -2.0], [3.0, 0.0]]);
        let b = report(&[[5.0, 4.0]]);
        let stats = NormalizationStats::combine(&[&a, &b]).unwrap();
        let s = &stats.features["action"];
        assert_eq!(s.count, 3);
        assert_eq!(s.mean, [3.0, 2.0 / 3.0]);
        let var0 = (4.0 + 0.0 + 4.0) / 3.0;
        let var1 = ((-2.0f64 - 2.0 / 3.0).powi(2) + (2.0f64 / 3.0).powi(2) + (4.0f64 - 2.0 / 3.0).powi(2)) / 3.0;
        assert!((s.std[0] - f64::sqrt(var0)).abs() < 1e-12 && (s.std[1] - var1.sqrt()).abs() < 1e-12);
        assert_eq!((s.min.clone(), s.max.clone()), (vec![1.0, -2.0], vec![5.0, 4.0]));
        assert_eq!((stats.source, stats.clients), (StatsSource::Federated, 2));
    }

    #[test]
    fn malformed_moments_are_refused_by_name() {
        let mut bad = report(&[[1.0, 2.0]]);
        bad.moments.get_mut("action").unwrap().sum_sq.pop();
        assert!(NormalizationStats::combine(&[&bad]).unwrap_err().contains("action"));
        let mut short = report(&[[1.0, 2.0]]);
        short.moments.remove("observation.state");
        assert!(NormalizationStats::combine(&[&short]).unwrap_err().contains("observation.state"));
        let wide = DataReport {
            own: None,
            moments: NORMALISED_FEATURES
                .iter()
                .map(|f| ((*f).to_owned(), FeatureMoments::of_rows(3, [[1.0f32, 2.0, 3.0].as_slice()])))
                .collect(),
        };
        assert!(NormalizationStats::combine(&[&report(&[[1.0, 2.0]]), &wide]).unwrap_err().contains("dimension"));
        assert!(NormalizationStats::combine(&[]).is_err());
    }

    #[test]
    fn signature_differences_name_both_sides() {
        let run = DatasetSignature {
            robot_type: Some("so100".into()),
            fps: 30,
            state_dim: 6,
            state_names: (0..6).map(|i| format!("j{i}")).collect(),
            action_dim: 6,
            action_names: (0..6).map(|i| format!("j{i}")).collect(),
            cameras: vec!["observation.images.top".into(), "observation.images.wrist".into()],
        };
        assert!(run.differences(&run).is_empty());
        let other = DatasetSignature {
            action_dim: 7,
            action_names: (0..7).map(|i| format!("j{i}")).collect(),
            cameras: vec!["observation.images.top".into()],
            ..run.clone()
        };
        let diffs = other.differences(&run);
        assert!(
            diffs.iter().any(|d| d.starts_with("action dimension: this dataset has 7, the run's has 6")),
            "{diffs:?}"
        );
        assert!(diffs.iter().any(|d| d.contains("lacks [\"observation.images.wrist\"]")), "{diffs:?}");
        assert_eq!(diffs.len(), 3, "{diffs:?}");
    }
}
