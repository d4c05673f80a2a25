//! Feature statistics as LeRobot stores them (`meta/stats.json` and the per-episode `stats/*` columns):
//! min, max, mean, std (population), count and the quantiles q01..q99.
//!
//! Per episode everything is exact in float64 (LeRobot itself approximates std and quantiles in float32
//! and with histograms); the dataset-level numbers combine the episodes the way LeRobot's
//! `aggregate_stats` does: exact pooled mean and variance, count-weighted mean of the quantiles.
//! Image statistics are per channel on values scaled to [0, 1], shaped [3, 1, 1] like LeRobot's.

use std::collections::BTreeMap;
use std::path::Path;

use serde_json::{Value, json};

use crate::error::{DataError, Result};

/// LeRobot's quantile keys and levels.
pub const QUANTILES: [(&str, f64); 5] = [("q01", 0.01), ("q10", 0.10), ("q50", 0.50), ("q90", 0.90), ("q99", 0.99)];

/// Shape of every statistic of an image feature: one value per channel.
pub const IMAGE_STATS_SHAPE: [usize; 3] = [3, 1, 1];

#[derive(Debug, Clone, PartialEq)]
pub struct FeatureStats {
    /// Shape of each statistic: `[dim]` for vectors and scalars, `[3, 1, 1]` for images.
    pub shape: Vec<usize>,
    pub min: Vec<f64>,
    pub max: Vec<f64>,
    pub mean: Vec<f64>,
    pub std: Vec<f64>,
    pub count: u64,
    /// One vector per entry of [`QUANTILES`], in that order.
    pub quantiles: Vec<Vec<f64>>,
}

/// Stats for every feature, by feature key.
pub type DatasetStats = BTreeMap<String, FeatureStats>;

impl FeatureStats {
    /// Exact stats of `rows` (each `dim` long), e.g. one episode's `observation.state`.
    pub fn from_rows(rows: &[Vec<f64>], dim: usize) -> Self {
        let n = rows.len();
        let mut columns = vec![Vec::with_capacity(n); dim];
        for row in rows {
            for (c, v) in columns.iter_mut().zip(row) {
                c.push(*v);
            }
        }
        let mut out = FeatureStats::empty(vec![dim], n as u64);
        for (d, col) in columns.iter_mut().enumerate() {
            let mean = col.iter().sum::<f64>() / n.max(1) as f64;
            let var = col.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n.max(1) as f64;
            col.sort_by(f64::total_cmp);
            out.min[d] = col.first().copied().unwrap_or(0.0);
            out.max[d] = col.last().copied().unwrap_or(0.0);
            out.mean[d] = mean;
            out.std[d] = var.sqrt();
            for (qi, (_, q)) in QUANTILES.iter().enumerate() {
                out.quantiles[qi][d] = quantile_sorted(|k| col[k], n, *q);
            }
        }
        out
    }

    /// Exact per-channel stats of 8-bit image pixels (scaled to [0, 1]) from 256-bin histograms,
    /// for an episode of `frames` frames.
    pub fn from_channel_histograms(histograms: &[[u64; 256]; 3], frames: u64) -> Self {
        let mut out = FeatureStats::empty(IMAGE_STATS_SHAPE.to_vec(), frames);
        for (c, h) in histograms.iter().enumerate() {
            let n: u64 = h.iter().sum();
            let value = |bin: usize| bin as f64 / 255.0;
            let mean = h.iter().enumerate().map(|(b, &k)| k as f64 * value(b)).sum::<f64>() / n.max(1) as f64;
            let var =
                h.iter().enumerate().map(|(b, &k)| k as f64 * (value(b) - mean).powi(2)).sum::<f64>() / n.max(1) as f64;
            out.min[c] = h.iter().position(|&k| k > 0).map_or(0.0, value);
            out.max[c] = h.iter().rposition(|&k| k > 0).map_or(0.0, value);
            out.mean[c] = mean;
            out.std[c] = var.sqrt();
            let mut cumulative = Vec::with_capacity(256);
            let mut acc = 0u64;
            for &k in h {
                acc += k;
                cumulative.push(acc);
            }
            // Value of the k-th smallest pixel (0-based): the first bin whose cumulative count exceeds k.
            let kth = |k: usize| value(cumulative.partition_point(|&cum| cum <= k as u64));
            for (qi, (_, q)) in QUANTILES.iter().enumerate() {
                out.quantiles[qi][c] = quantile_sorted(kth, n as usize, *q);
            }
        }
        out
    }

    fn empty(shape: Vec<usize>, count: u64) -> Self {
        let len: usize = shape.iter().product();
        FeatureStats {
            shape,
            min: vec![0.0; len],
            max: vec![0.0; len],
            mean: vec![0.0; len],
            std: vec![0.0; len],
            count,
            quantiles: vec![vec![0.0; len]; QUANTILES.len()],
        }
    }

    /// Combines per-episode stats into dataset stats (pooled mean/variance, count-weighted quantiles).
    pub fn aggregate(parts: &[&FeatureStats]) -> Option<FeatureStats> {
        let first = parts.first()?;
        let len = first.mean.len();
        let total: u64 = parts.iter().map(|p| p.count).sum();
        let mut out = FeatureStats::empty(first.shape.clone(), total);
        let weight = |p: &FeatureStats| p.count as f64 / total.max(1) as f64;
        for d in 0..len {
            out.min[d] = parts.iter().map(|p| p.min[d]).fold(f64::INFINITY, f64::min);
            out.max[d] = parts.iter().map(|p| p.max[d]).fold(f64::NEG_INFINITY, f64::max);
            let mean: f64 = parts.iter().map(|p| weight(p) * p.mean[d]).sum();
            let var: f64 = parts.iter().map(|p| weight(p) * (p.std[d].powi(2) + (p.mean[d] - mean).powi(2))).sum();
            out.mean[d] = mean;
            out.std[d] = var.sqrt();
            for qi in 0..QUANTILES.len() {
                out.quantiles[qi][d] = parts.iter().map(|p| weight(p) * p.quantiles[qi][d]).sum();
            }
        }
        Some(out)
    }

    /// The named statistics in LeRobot's order, each as (name, flat values).
    pub fn named_values(&self) -> Vec<(&'static str, &[f64])> {
        let mut out: Vec<(&'static str, &[f64])> =
            vec![("min", &self.min), ("max", &self.max), ("mean", &self.mean), ("std", &self.std)];
        for (qi, (name, _)) in QUANTILES.iter().enumerate() {
            out.push((name, &self.quantiles[qi]));
        }
        out
    }

    pub fn to_json(&self) -> Value {
        let mut map = serde_json::Map::new();
        for (name, values) in self.named_values().into_iter().take(4) {
            map.insert(name.into(), nest(values, &self.shape));
        }
        map.insert("count".into(), json!([self.count]));
        for (qi, (name, _)) in QUANTILES.iter().enumerate() {
            map.insert((*name).into(), nest(&self.quantiles[qi], &self.shape));
        }
        Value::Object(map)
    }

    /// Parses one feature's entry of `stats.json`; missing quantiles (older datasets) read as empty.
    pub fn from_json(value: &Value) -> Option<FeatureStats> {
        let (_, shape) = flatten(value.get("mean")?)?;
        Self::from_named(shape, |k| value.get(k).and_then(flatten).map(|(v, _)| v))
    }

    /// Builds the stats from each statistic's flat values by name (`"mean"`, `"count"`, `"q01"`...), as
    /// `stats.json` and the per-episode `stats/<feature>/<name>` columns store them; missing quantiles read as empty.
    pub fn from_named(shape: Vec<usize>, get: impl Fn(&str) -> Option<Vec<f64>>) -> Option<FeatureStats> {
        let count = get("count").and_then(|v| v.first().copied()).unwrap_or(0.0) as u64;
        Some(FeatureStats {
            shape,
            min: get("min")?,
            max: get("max")?,
            mean: get("mean")?,
            std: get("std")?,
            count,
            quantiles: QUANTILES.iter().map(|(k, _)| get(k).unwrap_or_default()).collect(),
        })
    }
}

/// numpy's default ("linear") quantile of `n` sorted values, `kth(k)` giving the k-th smallest.
fn quantile_sorted(kth: impl Fn(usize) -> f64, n: usize, q: f64) -> f64 {
    if n == 0 {
        return 0.0;
    }
    let pos = q * (n - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = (lo + 1).min(n - 1);
    let frac = pos - lo as f64;
    let (a, b) = (kth(lo), kth(hi));
    a + (b - a) * frac
}

/// Nests flat values into JSON arrays of `shape`.
fn nest(values: &[f64], shape: &[usize]) -> Value {
    match shape {
        [] | [_] => json!(values),
        [_, rest @ ..] => {
            let inner: usize = rest.iter().product();
            Value::Array(values.chunks(inner.max(1)).map(|c| nest(c, rest)).collect())
        }
    }
}

/// Flattens nested JSON number arrays, returning the values and the shape.
fn flatten(value: &Value) -> Option<(Vec<f64>, Vec<usize>)> {
    match value {
        Value::Number(n) => Some((vec![n.as_f64()?], vec![])),
        Value::Array(items) => {
            let mut values = Vec::new();
            let mut inner_shape = None;
            for item in items {
                let (v, s) = flatten(item)?;
                values.extend(v);
                inner_shape.get_or_insert(s);
            }
            let mut shape = vec![items.len()];
            shape.extend(inner_shape.unwrap_or_default());
            Some((values, shape))
        }
        _ => None,
    }
}

pub fn save_stats(path: &Path, stats: &DatasetStats) -> Result<()> {
    let map: serde_json::Map<String, Value> = stats.iter().map(|(k, s)| (k.clone(), s.to_json())).collect();
    crate::info::write_json(path, &Value::Object(map))
}

pub fn load_stats(path: &Path) -> Result<DatasetStats> {
    let bytes = std::fs::read(path).map_err(|e| DataError::io(path, e))?;
    parse_stats(path, &bytes)
}

/// Parses a `meta/stats.json` (`path` names it in errors).
pub fn parse_stats(path: &Path, bytes: &[u8]) -> Result<DatasetStats> {
    let value: Value = serde_json::from_slice(bytes)
        .map_err(|e| DataError::InvalidJson { path: path.to_path_buf(), reason: e.to_string() })?;
    let object = value.as_object().ok_or_else(|| DataError::InvalidJson {
        path: path.to_path_buf(),
        reason: "top level is not an object".into(),
    })?;
    object
        .iter()
        .map(|(k, v)| {
            FeatureStats::from_json(v).map(|s| (k.clone(), s)).ok_or_else(|| DataError::InvalidJson {
                path: path.to_path_buf(),
                reason: format!("stats for {k:?} lack min/max/mean/std"),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vector_stats_match_numpy() {
        let rows: Vec<Vec<f64>> = [1.0, 2.0, 3.0, 4.0, 10.0].iter().map(|&v| vec![v]).collect();
        let s = FeatureStats::from_rows(&rows, 1);
        assert_eq!(s.mean, vec![4.0]);
        assert!((s.std[0] - 10.0f64.sqrt()).abs() < 1e-12);
        // numpy.quantile([1,2,3,4,10], 0.9) == 7.6
        assert!((s.quantiles[3][0] - 7.6).abs() < 1e-12);
    }

    #[test]
    fn aggregate_equals_stats_of_concatenation() {
        let a: Vec<Vec<f64>> = (0..7).map(|i| vec![i as f64, (i * i) as f64]).collect();
        let b: Vec<Vec<f64>> = (0..5).map(|i| vec![-(i as f64), 3.5 * i as f64]).collect();
        let all: Vec<Vec<f64>> = a.iter().chain(&b).cloned().collect();
        let (sa, sb, sall) =
            (FeatureStats::from_rows(&a, 2), FeatureStats::from_rows(&b, 2), FeatureStats::from_rows(&all, 2));
        let agg = FeatureStats::aggregate(&[&sa, &sb]).expect("two parts");
        for d in 0..2 {
            assert!((agg.mean[d] - sall.mean[d]).abs() < 1e-12);
            assert!((agg.std[d] - sall.std[d]).abs() < 1e-12);
            assert_eq!(agg.min[d], sall.min[d]);
            assert_eq!(agg.max[d], sall.max[d]);
        }
        assert_eq!(agg.count, 12);
    }

    #[test]
    fn histogram_stats_equal_direct_stats() {
        let pixels: Vec<u8> = (0..300u32).map(|i| ((i * 37) % 256) as u8).collect();
        let mut hist = [[0u64; 256]; 3];
        for &p in &pixels {
            for h in hist.iter_mut() {
                h[p as usize] += 1;
            }
        }
        let image = FeatureStats::from_channel_histograms(&hist, 1);
        let rows: Vec<Vec<f64>> = pixels.iter().map(|&p| vec![f64::from(p) / 255.0]).collect();
        let direct = FeatureStats::from_rows(&rows, 1);
        assert!((image.mean[0] - direct.mean[0]).abs() < 1e-12);
        assert!((image.std[0] - direct.std[0]).abs() < 1e-12);
        for qi in 0..QUANTILES.len() {
            assert!((image.quantiles[qi][0] - direct.quantiles[qi][0]).abs() < 1e-12);
        }
    }

    #[test]
    fn json_round_trip_keeps_image_shape() {
        let hist = [[1u64; 256]; 3];
        let s = FeatureStats::from_channel_histograms(&hist, 4);
        let json = s.to_json();
        assert_eq!(json["mean"].as_array().map(Vec::len), Some(3));
        assert!(json["mean"][0][0][0].is_number());
        assert_eq!(FeatureStats::from_json(&json), Some(s));
    }
}
