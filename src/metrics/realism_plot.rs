//! `v2ce eval realism --plot`: the distributions behind the realism statistics, the real
//! stream's and the simulated one's side by side, one panel each, as a PNG.

use std::path::Path;

use super::realism::Report;
use crate::error::{Error, Result};

/// Draws `report`'s curves ([`super::realism::Curve`]) at `path`.
pub fn plot(report: &Report, path: &Path) -> Result<()> {
    use plotters::prelude::*;
    if report.curves.is_empty() {
        return Err(Error::invalid("plot", "no distributions to draw"));
    }
    crate::plot::register_font()?;
    let fail = |e: &dyn std::fmt::Display| Error::invalid("plot", e.to_string());
    let n = report.curves.len() as u32;
    let root = BitMapBackend::new(path, (520 * n, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(&e))?;
    let panels = root.split_evenly((1, report.curves.len()));
    let real_colour = RGBColor(31, 119, 180);
    let sim_colour = RGBColor(255, 127, 14);
    for (area, curve) in panels.iter().zip(&report.curves) {
        let lo = curve.xs.first().copied().unwrap_or(0.0);
        let hi = curve.xs.last().copied().unwrap_or(1.0);
        let hi = if hi > lo { hi } else { lo + 1.0 };
        let top = curve
            .real
            .iter()
            .chain(&curve.sim)
            .copied()
            .fold(0.0f64, f64::max);
        let top = if top > 0.0 { top * 1.1 } else { 1.0 };
        let mut chart = ChartBuilder::on(area)
            .caption(curve.title, ("sans-serif", 16))
            .margin(14)
            .x_label_area_size(40)
            .y_label_area_size(56)
            .build_cartesian_2d(lo..hi, 0f64..top)
            .map_err(|e| fail(&e))?;
        chart
            .configure_mesh()
            .x_desc(curve.x_label)
            .y_desc("share")
            .light_line_style(WHITE)
            .label_style(("sans-serif", 12))
            .draw()
            .map_err(|e| fail(&e))?;
        for (name, colour, values) in [
            ("real", real_colour, &curve.real),
            ("simulated", sim_colour, &curve.sim),
        ] {
            chart
                .draw_series(LineSeries::new(
                    curve.xs.iter().copied().zip(values.iter().copied()),
                    colour.stroke_width(2),
                ))
                .map_err(|e| fail(&e))?
                .label(name)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], colour));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 12))
            .draw()
            .map_err(|e| fail(&e))?;
    }
    root.present().map_err(|e| fail(&e))
}
