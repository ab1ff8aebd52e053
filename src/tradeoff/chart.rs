//! The trade-off plot: TF1 against speed with the Pareto front, drawn with plotters.

use super::{pareto, Row};
use crate::error::Result;

/// Draws TF1 against speed (pairs/s, log scale), one panel per scene, every row a point (by
/// tier) and the Pareto front ([`pareto`]) a line through its labelled points, as a PNG at
/// `path`.
pub fn plot(rows: &[Row], path: &std::path::Path) -> Result<()> {
    use plotters::prelude::*;
    crate::plot::register_font()?;
    let mut scenes: Vec<&str> = Vec::new();
    for r in rows {
        if !scenes.contains(&r.scene.as_str()) {
            scenes.push(&r.scene);
        }
    }
    if scenes.is_empty() {
        return Err(crate::Error::invalid("plot", "no rows to plot"));
    }
    let fail = |e: &dyn std::fmt::Display| crate::Error::invalid("plot", e.to_string());
    let panel_w = 720u32;
    let root = BitMapBackend::new(path, (panel_w * scenes.len() as u32, 560)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(&e))?;
    let panels = root.split_evenly((1, scenes.len()));
    for (area, scene) in panels.iter().zip(&scenes) {
        let of: Vec<&Row> = rows.iter().filter(|r| r.scene == *scene).collect();
        // Speeds on a log10 axis, whole decades.
        let x = |r: &Row| r.pairs_per_s.max(1e-3).log10();
        let lo = of
            .iter()
            .map(|r| x(r))
            .fold(f64::INFINITY, f64::min)
            .floor();
        let hi = of
            .iter()
            .map(|r| x(r))
            .fold(f64::NEG_INFINITY, f64::max)
            .ceil();
        let hi = if hi > lo { hi } else { lo + 1.0 };
        let top = of.iter().map(|r| r.tf1).fold(0.0f64, f64::max);
        let mut chart = ChartBuilder::on(area)
            .caption(format!("TF1 against speed: {scene}"), ("sans-serif", 18))
            .margin(16)
            .x_label_area_size(44)
            .y_label_area_size(50)
            .build_cartesian_2d(lo..hi, 0f64..(top * 1.15).clamp(0.05, 1.0))
            .map_err(|e| fail(&e))?;
        chart
            .configure_mesh()
            .x_labels((hi - lo) as usize + 1)
            .x_label_formatter(&|v| format!("{}", 10f64.powf(v.round())))
            .x_desc("frame pairs per second (log scale)")
            .y_desc("TF1")
            .light_line_style(WHITE)
            .label_style(("sans-serif", 13))
            .draw()
            .map_err(|e| fail(&e))?;
        for (name, colour, physics) in [
            ("physics tier", RGBColor(31, 119, 180), true),
            ("learned tier", RGBColor(214, 39, 40), false),
        ] {
            let points = of
                .iter()
                .filter(|r| r.setting.starts_with("physics") == physics)
                .map(|r| Circle::new((x(r), r.tf1), 4, colour.filled()));
            chart
                .draw_series(points)
                .map_err(|e| fail(&e))?
                .label(name)
                .legend(move |(x, y)| Circle::new((x + 8, y), 4, colour.filled()));
        }
        let mut front = pareto(rows, scene);
        front.sort_by(|a, b| a.pairs_per_s.total_cmp(&b.pairs_per_s));
        chart
            .draw_series(LineSeries::new(
                front.iter().map(|r| (x(r), r.tf1)),
                BLACK.stroke_width(1),
            ))
            .map_err(|e| fail(&e))?
            .label("Pareto front (speed, TF1)")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLACK));
        let mid = (lo + hi) / 2.0;
        chart
            .draw_series(front.iter().enumerate().map(|(i, r)| {
                use plotters::style::text_anchor::{HPos, Pos, VPos};
                // Left of points in the right half, right of the others; alternately above
                // and below, so neighbouring labels part.
                let (h, dx) = if x(r) > mid {
                    (HPos::Right, -8)
                } else {
                    (HPos::Left, 8)
                };
                let (v, dy) = if i % 2 == 0 {
                    (VPos::Bottom, -6)
                } else {
                    (VPos::Top, 6)
                };
                let style = ("sans-serif", 12)
                    .into_font()
                    .color(&BLACK)
                    .pos(Pos::new(h, v));
                EmptyElement::at((x(r), r.tf1)) + Text::new(r.setting.clone(), (dx, dy), style)
            }))
            .map_err(|e| fail(&e))?;
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .draw()
            .map_err(|e| fail(&e))?;
    }
    root.present().map_err(|e| fail(&e))?;
    Ok(())
}
