//! PNG plots of a figure per round: one line (the mean over seeds) and a shaded 95% band per arm (experiments), or
//! one line per run on a log scale (a search's trials over its rungs).

use std::collections::BTreeMap;
use std::ops::RangeInclusive;
use std::path::Path;

use plotters::prelude::*;

use super::stats::Interval;

/// One arm's figure along an axis of whole numbers (rounds, samples), over its seeds.
pub struct Curve {
    pub name: String,
    /// (x, interval over the seeds that have a value at that x).
    pub points: Vec<(u64, Interval)>,
}

impl Curve {
    /// At each x, the mean and 95% interval over `runs` (each a list of (x, value)).
    pub fn over_seeds(name: &str, runs: impl Iterator<Item = Vec<(u64, f64)>>) -> Self {
        let mut by_x: BTreeMap<u64, Vec<f64>> = BTreeMap::new();
        for run in runs {
            for (x, value) in run {
                by_x.entry(x).or_default().push(value);
            }
        }
        let points = by_x.into_iter().filter_map(|(r, v)| Some((r, Interval::t(&v)?))).collect();
        Self { name: name.to_owned(), points }
    }
}

/// Draws `curves` into the PNG at `path` (800 x 480). `range` is what the figure can take (a success rate lies in
/// [0, 1], a loss at or above 0): a t band over a few seeds reaches beyond it, and is drawn clipped to it.
pub fn plot_curves(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    range: RangeInclusive<f64>,
    curves: &[Curve],
) -> anyhow::Result<()> {
    let clip = |y: f64| y.clamp(*range.start(), *range.end());
    let points = || curves.iter().flat_map(|c| c.points.iter());
    let x_max = points().map(|(r, _)| *r).max().unwrap_or(1).max(1) as f64;
    let y_min = points().map(|(_, i)| clip(i.ci95_low)).fold(f64::INFINITY, f64::min);
    let y_max = points().map(|(_, i)| clip(i.ci95_high)).fold(f64::NEG_INFINITY, f64::max);
    let (y_min, y_max) = if y_min.is_finite() && y_max > y_min { (y_min, y_max) } else { (0.0, 1.0) };
    let pad = (y_max - y_min) * 0.05;
    let root = BitMapBackend::new(path, (800, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(draw_error)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(64)
        .build_cartesian_2d(0f64..x_max, (y_min - pad)..(y_max + pad))
        .map_err(draw_error)?;
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc(y_label)
        // Whole numbers on x; on y, a tick a rounding error below 0 reads 0, not -0.0.
        .x_label_formatter(&|x| format!("{x:.0}"))
        .y_label_formatter(&|y| if y.abs() < 5e-5 { "0".to_owned() } else { format!("{}", (y * 1e4).round() / 1e4) })
        .draw()
        .map_err(draw_error)?;
    for (i, curve) in curves.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        let band: Vec<(f64, f64)> = curve
            .points
            .iter()
            .map(|(r, c)| (*r as f64, clip(c.ci95_high)))
            .chain(curve.points.iter().rev().map(|(r, c)| (*r as f64, clip(c.ci95_low))))
            .collect();
        chart.draw_series(std::iter::once(Polygon::new(band, color.mix(0.2).filled()))).map_err(draw_error)?;
        let line = curve.points.iter().map(|(r, c)| (*r as f64, c.mean));
        chart
            .draw_series(LineSeries::new(line, color.stroke_width(2)))
            .map_err(draw_error)?
            .label(&curve.name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
    }
    chart.configure_series_labels().background_style(WHITE.mix(0.85)).border_style(BLACK).draw().map_err(draw_error)?;
    root.present().map_err(draw_error)?;
    Ok(())
}

/// One run's figure at some rounds; labelled lines are drawn bold, in colour and in the legend, the others thin and
/// grey.
pub struct Line {
    pub label: Option<String>,
    pub points: Vec<(u64, f64)>,
}

/// Draws `lines` into the PNG at `path` (800 x 480), the figure on a log scale (points at or below 0 left out):
/// drawn as its log10 on a linear axis whose labels give the figure, so that a range narrower than a power of ten
/// still has its ticks.
pub fn plot_log_lines(path: &Path, title: &str, y_label: &str, lines: &[Line]) -> anyhow::Result<()> {
    let logged: Vec<Vec<(f64, f64)>> = lines
        .iter()
        .map(|l| {
            l.points.iter().filter(|(_, y)| *y > 0.0 && y.is_finite()).map(|(r, y)| (*r as f64, y.log10())).collect()
        })
        .collect();
    let points = || logged.iter().flatten();
    let x_max = points().map(|(r, _)| *r).fold(1.0, f64::max);
    let y_min = points().map(|(_, y)| *y).fold(f64::INFINITY, f64::min);
    let y_max = points().map(|(_, y)| *y).fold(f64::NEG_INFINITY, f64::max);
    let (y_min, y_max) = if y_min.is_finite() && y_max > y_min { (y_min, y_max) } else { (-1.0, 1.0) };
    let pad = (y_max - y_min) * 0.05;
    let root = BitMapBackend::new(path, (800, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(draw_error)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(64)
        .build_cartesian_2d(0f64..x_max * 1.05, (y_min - pad)..(y_max + pad))
        .map_err(draw_error)?;
    chart
        .configure_mesh()
        .x_desc("round")
        .y_desc(y_label)
        // Rounds are whole: at most one label per round.
        .x_labels((x_max as usize + 1).min(11))
        .x_label_formatter(&|x| format!("{x:.0}"))
        .y_label_formatter(&|y| format!("{:.3}", 10f64.powf(*y)))
        .draw()
        .map_err(draw_error)?;
    // The unlabelled first, so that the labelled are drawn over them.
    let order = (0..lines.len())
        .filter(|&i| lines[i].label.is_none())
        .chain((0..lines.len()).filter(|&i| lines[i].label.is_some()));
    let mut colours = 0;
    for i in order {
        let points = logged[i].clone();
        let Some(label) = &lines[i].label else {
            let grey = RGBColor(150, 150, 150);
            chart.draw_series(points.iter().map(|p| Circle::new(*p, 2, grey.filled()))).map_err(draw_error)?;
            chart.draw_series(LineSeries::new(points, grey.stroke_width(1))).map_err(draw_error)?;
            continue;
        };
        let colour = Palette99::pick(colours).to_rgba();
        colours += 1;
        chart.draw_series(points.iter().map(|p| Circle::new(*p, 4, colour.filled()))).map_err(draw_error)?;
        chart
            .draw_series(LineSeries::new(points, colour.stroke_width(3)))
            .map_err(draw_error)?
            .label(label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(3)));
    }
    chart.configure_series_labels().background_style(WHITE.mix(0.85)).border_style(BLACK).draw().map_err(draw_error)?;
    root.present().map_err(draw_error)?;
    Ok(())
}

fn draw_error(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow::anyhow!("drawing the plot: {e}")
}
