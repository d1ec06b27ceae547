//! Figures of training curves: one panel per scene side by side, methods overlaid (the mean
//! over seeds as a line, their range as a shaded band), a shared legend below; written as
//! PNG and SVG. Text uses DejaVu Sans compiled into the binary (the `dejavu` crate), so
//! nothing depends on the fonts a machine has.

use std::path::Path;
use std::sync::Once;

use anyhow::{Context, anyhow};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};

use crate::report::aggregate::BandPoint;

pub const WIDTH: u32 = 1200;
pub const HEIGHT: u32 = 500;
const FONT: &str = "sans-serif";
const LEGEND_HEIGHT: u32 = 44;

/// Okabe & Ito's colour-blind-safe palette (yellow darkened to read on white), in the order
/// methods are given.
const PALETTE: [RGBColor; 8] = [
    RGBColor(0, 114, 178),
    RGBColor(213, 94, 0),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(230, 159, 0),
    RGBColor(86, 180, 233),
    RGBColor(0, 0, 0),
    RGBColor(150, 130, 0),
];

pub fn colour(index: usize) -> RGBColor {
    PALETTE[index % PALETTE.len()]
}

/// One method's curve in one panel.
pub struct Series {
    /// Index into the palette: the method's place in the report's method order, so a method
    /// has one colour in every panel and figure.
    pub colour: usize,
    pub band: Vec<BandPoint>,
}

/// One scene.
pub struct Panel {
    pub title: String,
    pub series: Vec<Series>,
}

pub struct Figure {
    pub title: String,
    pub y_label: String,
    /// A share of episodes: the y axis is fixed to [0, 1] (with a margin).
    pub share: bool,
    pub panels: Vec<Panel>,
    /// (method, colour) for the legend, in order.
    pub legend: Vec<(String, usize)>,
}

fn register_fonts() {
    static FONTS: Once = Once::new();
    FONTS.call_once(|| {
        // The bytes are a valid TrueType font compiled in; a failure would leave plotters
        // without text, and drawing then reports the missing font as an error.
        let _ = register_font(FONT, FontStyle::Normal, dejavu::sans::regular());
        let _ = register_font(FONT, FontStyle::Bold, dejavu::sans::bold());
    });
}

/// Writes `figure` to `png` and `svg`.
pub fn write(figure: &Figure, png_path: &Path, svg_path: &Path) -> anyhow::Result<()> {
    register_fonts();
    let mut pixels = vec![0u8; (WIDTH * HEIGHT * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, (WIDTH, HEIGHT)).into_drawing_area();
        draw(figure, &root).with_context(|| format!("drawing {}", png_path.display()))?;
        root.present()
            .map_err(|e| anyhow!("rendering {}: {e}", png_path.display()))?;
    }
    write_png(png_path, &pixels)?;
    let root = SVGBackend::new(svg_path, (WIDTH, HEIGHT)).into_drawing_area();
    draw(figure, &root).with_context(|| format!("drawing {}", svg_path.display()))?;
    root.present()
        .map_err(|e| anyhow!("writing {}: {e}", svg_path.display()))?;
    Ok(())
}

fn write_png(path: &Path, rgb: &[u8]) -> anyhow::Result<()> {
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), WIDTH, HEIGHT);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder
        .write_header()
        .with_context(|| format!("writing {}", path.display()))?;
    writer
        .write_image_data(rgb)
        .with_context(|| format!("writing {}", path.display()))?;
    writer
        .finish()
        .with_context(|| format!("writing {}", path.display()))
}

/// "0", "500", "20k", "1.5M": agent-step counts readable at a glance.
pub fn steps_label(x: f64) -> String {
    let a = x.abs();
    let (scaled, suffix) = if a >= 1e6 {
        (x / 1e6, "M")
    } else if a >= 1e3 {
        (x / 1e3, "k")
    } else {
        (x, "")
    };
    let text = format!("{scaled:.1}");
    let text = text.strip_suffix(".0").unwrap_or(&text);
    format!("{text}{suffix}")
}

/// Decimals that tell apart the ticks of an axis spanning `span` with about 7 labels, the
/// same for every tick: "6.10", "6.12"; "0.2", "0.4"; "20", "40".
pub fn tick_decimals(span: f64) -> usize {
    let step = span.abs() / 7.0;
    if step <= 0.0 || !step.is_finite() {
        return 2;
    }
    (-step.log10()).ceil().clamp(0.0, 4.0) as usize
}

pub fn tick_label(y: f64, decimals: usize) -> String {
    let text = format!("{y:.decimals$}");
    // No "-0.0" for a tick a rounding error below zero.
    if text
        .trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        text.trim_start_matches('-').to_string()
    } else {
        text
    }
}

/// The y range every panel shares, so scenes compare at a glance.
fn y_range(figure: &Figure) -> (f64, f64) {
    if figure.share {
        // A little room so lines at 0 and 1 stay clear of the frame.
        return (-0.02, 1.02);
    }
    let (low, high) = figure
        .panels
        .iter()
        .flat_map(|p| &p.series)
        .flat_map(|s| &s.band)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p.min), hi.max(p.max))
        });
    if !low.is_finite() || !high.is_finite() {
        return (0.0, 1.0);
    }
    let pad = if high > low {
        0.06 * (high - low)
    } else {
        low.abs().max(1.0) * 0.1
    };
    let low = if low >= 0.0 {
        (low - pad).max(0.0)
    } else {
        low - pad
    };
    (low, high + pad)
}

fn draw<DB: DrawingBackend>(figure: &Figure, root: &DrawingArea<DB, Shift>) -> anyhow::Result<()> {
    let failed = |e: DrawingAreaErrorKind<DB::ErrorType>| anyhow!("{e}");
    root.fill(&WHITE).map_err(failed)?;
    let title_style = (FONT, 24).into_font().style(FontStyle::Bold);
    let body = root.titled(&figure.title, title_style).map_err(failed)?;
    let (plots, legend) = body.split_vertically(body.dim_in_pixel().1 - LEGEND_HEIGHT);
    let x_end = figure
        .panels
        .iter()
        .flat_map(|p| &p.series)
        .flat_map(|s| s.band.last())
        .map(|p| p.x)
        .fold(0.0, f64::max)
        .max(1.0);
    let (y_low, y_high) = y_range(figure);
    let decimals = tick_decimals(y_high - y_low);
    let areas = plots.split_evenly((1, figure.panels.len().max(1)));
    for (panel, area) in figure.panels.iter().zip(&areas) {
        let mut chart = ChartBuilder::on(area)
            .caption(&panel.title, (FONT, 19))
            .margin_left(12)
            .margin_right(22)
            .margin_top(6)
            .x_label_area_size(44)
            .y_label_area_size(66)
            .build_cartesian_2d(0.0..x_end, y_low..y_high)
            .map_err(failed)?;
        chart
            .configure_mesh()
            .x_desc("agent-steps")
            .y_desc(figure.y_label.as_str())
            .x_labels(7)
            .y_labels(7)
            .x_label_formatter(&|x| steps_label(*x))
            .y_label_formatter(&|y| tick_label(*y, decimals))
            .label_style((FONT, 14))
            .axis_desc_style((FONT, 15))
            .max_light_lines(1)
            .light_line_style(RGBColor(240, 240, 240))
            .bold_line_style(RGBColor(214, 214, 214))
            .draw()
            .map_err(failed)?;
        if panel.series.iter().all(|s| s.band.is_empty()) {
            let centre = ((x_end / 2.0), (y_low + y_high) / 2.0);
            chart
                .draw_series(std::iter::once(Text::new(
                    "no runs",
                    centre,
                    (FONT, 16).into_font().color(&RGBColor(120, 120, 120)),
                )))
                .map_err(failed)?;
        }
        for series in &panel.series {
            let colour = self::colour(series.colour);
            // The range over seeds, where more than one seed reaches.
            let spread: Vec<&BandPoint> = series.band.iter().filter(|p| p.seeds > 1).collect();
            if spread.len() > 1 {
                let outline: Vec<(f64, f64)> = spread
                    .iter()
                    .map(|p| (p.x, p.max))
                    .chain(spread.iter().rev().map(|p| (p.x, p.min)))
                    .collect();
                chart
                    .draw_series(std::iter::once(Polygon::new(
                        outline,
                        colour.mix(0.18).filled(),
                    )))
                    .map_err(failed)?;
            }
            chart
                .draw_series(LineSeries::new(
                    series.band.iter().map(|p| (p.x, p.mean)),
                    colour.stroke_width(3),
                ))
                .map_err(failed)?;
            if series.band.len() == 1 {
                let p = series.band[0];
                chart
                    .draw_series(std::iter::once(Circle::new(
                        (p.x, p.mean),
                        4,
                        colour.filled(),
                    )))
                    .map_err(failed)?;
            }
        }
    }
    draw_legend(figure, &legend).map_err(failed)?;
    Ok(())
}

/// Method names with their colours in one centred row, and what the shading means.
fn draw_legend<DB: DrawingBackend>(
    figure: &Figure,
    area: &DrawingArea<DB, Shift>,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let text_style = (FONT, 16).into_font().color(&BLACK);
    let note = "lines: mean over seeds · shading: range over seeds";
    let mut entries: Vec<(i32, &str, Option<RGBColor>)> = Vec::new();
    for (name, colour) in &figure.legend {
        let (w, _) = area.estimate_text_size(name, &text_style)?;
        entries.push((w as i32 + 34 + 26, name, Some(self::colour(*colour))));
    }
    let note_style = (FONT, 14).into_font().color(&RGBColor(100, 100, 100));
    let (note_w, _) = area.estimate_text_size(note, &note_style)?;
    entries.push((note_w as i32, note, None));
    let total: i32 = entries.iter().map(|e| e.0).sum();
    let (width, height) = area.dim_in_pixel();
    let mut x = ((width as i32 - total) / 2).max(8);
    let y = height as i32 / 2;
    for (w, text, colour) in entries {
        match colour {
            Some(c) => {
                area.draw(&PathElement::new(
                    vec![(x, y), (x + 26, y)],
                    c.stroke_width(4),
                ))?;
                area.draw(&Text::new(text, (x + 34, y - 9), text_style.clone()))?;
            }
            None => area.draw(&Text::new(text, (x, y - 8), note_style.clone()))?,
        }
        x += w;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn step_labels_are_short() {
        assert_eq!(steps_label(0.0), "0");
        assert_eq!(steps_label(500.0), "500");
        assert_eq!(steps_label(20_000.0), "20k");
        assert_eq!(steps_label(1_500_000.0), "1.5M");
        assert_eq!(steps_label(2_340.0), "2.3k");
        assert_eq!(tick_decimals(0.12), 2);
        assert_eq!(tick_decimals(1.04), 1);
        assert_eq!(tick_decimals(70.0), 0);
        assert_eq!(tick_label(6.1, 2), "6.10");
        assert_eq!(tick_label(0.8, 1), "0.8");
        assert_eq!(tick_label(40.0, 0), "40");
        assert_eq!(tick_label(-0.0001, 1), "0.0");
    }
}
