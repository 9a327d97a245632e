//! One PNG per evaluated recording: true against estimated heading, true subject against the
//! node's identity, and the shape filter's per-frame distance with its gate and its change
//! statistic with the threshold. Drawn with plotters; the font (DejaVu Sans Mono, `assets/fonts/`)
//! is compiled in, so plots look the same on a machine without fonts.

use std::path::Path;
use std::sync::Once;

use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use plotters::style::FontStyle;

use super::RecordingReport;

#[derive(Debug, thiserror::Error)]
#[error("plot: {0}")]
pub struct PlotError(pub String);

const FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSansMono.ttf");

fn register_font() -> Result<(), PlotError> {
    static REGISTER: Once = Once::new();
    let mut result = Ok(());
    REGISTER.call_once(|| {
        result = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT)
            .map_err(|_| PlotError("the compiled-in font does not load".into()));
    });
    result
}

fn err<E: std::fmt::Display>(e: E) -> PlotError {
    PlotError(e.to_string())
}

type Area<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;
type Chart<'a, 'b> = ChartContext<'b, BitMapBackend<'a>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// One panel over the frame index: caption, axes and mesh drawn.
fn panel<'a, 'b>(
    area: &'b Area<'a>,
    caption: &str,
    frames: f64,
    y: std::ops::Range<f64>,
) -> Result<Chart<'a, 'b>, PlotError> {
    let mut chart = ChartBuilder::on(area)
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(60)
        .caption(caption, ("sans-serif", 16))
        .build_cartesian_2d(0.0..frames, y)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("frame")
        .label_style(("sans-serif", 13))
        .draw()
        .map_err(err)?;
    Ok(chart)
}

fn wrapped_deg(angle: f64) -> f64 {
    super::metrics::wrap(angle).to_degrees()
}

/// Writes `path`: three panels over the frame index. `threshold` is the change detector's, when
/// it has one.
pub fn recording(path: &Path, recording: &RecordingReport, gate: f64, threshold: Option<f64>) -> Result<(), PlotError> {
    register_font()?;
    let rows = &recording.rows;
    let last = rows.iter().map(|r| r.frame).max().unwrap_or(1).max(1) as f64;
    let root = BitMapBackend::new(path, (1400, 1000)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let title = format!(
        "{}: heading (filtered) median {:.1} deg, changes found {}/{} ({} false)",
        recording.stream,
        recording
            .heading_filtered
            .as_ref()
            .and_then(|h| h.median_deg)
            .unwrap_or(f64::NAN),
        recording.changes.as_ref().map(|c| c.found).unwrap_or(0),
        recording.changes.as_ref().map(|c| c.true_changes).unwrap_or(0),
        recording.changes.as_ref().map(|c| c.false_changes).unwrap_or(0),
    );
    let root = root.titled(&title, ("sans-serif", 22)).map_err(err)?;
    let panels = root.split_evenly((3, 1));

    // Heading, wrapped to (-180, 180].
    let mut chart = panel(
        &panels[0],
        "heading (deg): truth black, raw grey, filtered blue",
        last,
        -180.0..180.0,
    )?;
    let dots = |value: fn(&super::Row) -> f64, color: RGBColor, size: i32| {
        rows.iter()
            .map(move |r| Circle::new((r.frame as f64, wrapped_deg(value(r))), size, color.filled()))
    };
    chart
        .draw_series(dots(|r| r.raw_yaw, RGBColor(170, 170, 170), 2))
        .map_err(err)?;
    chart
        .draw_series(dots(|r| r.filtered_yaw, RGBColor(30, 90, 220), 2))
        .map_err(err)?;
    chart.draw_series(dots(|r| r.true_yaw, BLACK, 1)).map_err(err)?;

    // Identity: the true subject and the node's identity (both count from 0).
    let top = rows
        .iter()
        .map(|r| (r.subject as f64).max(r.identity as f64))
        .fold(1.0, f64::max)
        + 0.5;
    let mut chart = panel(
        &panels[1],
        "identity: true subject black, node's identity red",
        last,
        -0.5..top,
    )?;
    chart
        .draw_series(LineSeries::new(
            rows.iter().map(|r| (r.frame as f64, r.subject as f64)),
            BLACK.stroke_width(3),
        ))
        .map_err(err)?;
    chart
        .draw_series(LineSeries::new(
            rows.iter().map(|r| (r.frame as f64, r.identity as f64 + 0.05)),
            RED.stroke_width(2),
        ))
        .map_err(err)?;

    // The shape filter: distance and gate; change statistic and threshold.
    let high = rows
        .iter()
        .map(|r| r.distance.max(r.change_statistic))
        .filter(|v| v.is_finite())
        .fold(gate.max(threshold.unwrap_or(0.0)) * 1.5, f64::max)
        .min(gate.max(threshold.unwrap_or(0.0)) * 6.0);
    let mut chart = panel(
        &panels[2],
        "shape: distance grey (gate dashed), change statistic orange (threshold dashed)",
        last,
        0.0..high,
    )?;
    chart
        .draw_series(LineSeries::new(
            rows.iter().map(|r| (r.frame as f64, r.distance.min(high))),
            RGBColor(130, 130, 130),
        ))
        .map_err(err)?;
    chart
        .draw_series(DashedLineSeries::new(
            [(0.0, gate), (last, gate)],
            6,
            4,
            RGBColor(90, 90, 90).stroke_width(1),
        ))
        .map_err(err)?;
    let orange = RGBColor(235, 140, 20);
    chart
        .draw_series(LineSeries::new(
            rows.iter().map(|r| (r.frame as f64, r.change_statistic.min(high))),
            orange.stroke_width(2),
        ))
        .map_err(err)?;
    if let Some(h) = threshold {
        chart
            .draw_series(DashedLineSeries::new(
                [(0.0, h), (last, h)],
                6,
                4,
                orange.stroke_width(1),
            ))
            .map_err(err)?;
    }
    chart
        .draw_series(
            rows.iter()
                .filter(|r| r.change_reported)
                .map(|r| TriangleMarker::new((r.frame as f64, high * 0.95), 7, RED.filled())),
        )
        .map_err(err)?;
    root.present()
        .map_err(|e| PlotError(format!("{}: {e}", path.display())))?;
    Ok(())
}
