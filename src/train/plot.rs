//! `curves.png`: a training run's curves, drawn with plotters (bitmap backend) and set in
//! DejaVu Sans (bundled through the `dejavu` crate, so every machine draws the same text; the
//! font's licence is in docs/building.md).
//!
//! Left panel: the training loss per iteration, (1 − λ)·L1 + λ·D-SSIM as the optimiser sees it,
//! on a log axis. Right panel: PSNR in dB of the training view of each iteration (grey) and of
//! the held-out views at each evaluation (red dots). Both panels shade the densification window
//! and draw a dashed orange line at every opacity reset (the schedule of Inria's 3DGS, as
//! `train` runs it).
use std::path::Path;
use std::sync::OnceLock;

use anyhow::{anyhow, Result};
use plotters::coord::combinators::WithKeyPoints;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use plotters::style::FontStyle;

/// Figure size in pixels.
pub const WIDTH: u32 = 1200;
pub const HEIGHT: u32 = 500;
/// Height of the figure's title band and of each panel's caption, x-axis and y-axis label
/// areas, in pixels (a test reads text in these regions).
pub const TITLE_HEIGHT: u32 = 40;
pub const X_LABEL_HEIGHT: u32 = 50;
pub const Y_LABEL_WIDTH: u32 = 75;
const CAPTION: u32 = 22;
const MARGIN: u32 = 12;
const FONT: &str = "sans-serif";

/// What a figure shows: per-iteration series and the schedule's events.
#[derive(Clone, Debug, Default)]
pub struct Curves {
    pub title: String,
    /// (iteration, loss)
    pub loss: Vec<(u64, f64)>,
    /// (iteration, training-view PSNR in dB)
    pub train_psnr: Vec<(u64, f64)>,
    /// (iteration, held-out PSNR in dB)
    pub test_psnr: Vec<(u64, f64)>,
    /// Iterations `[from, until)` in which the scene was densified (None: no densification).
    pub densify: Option<(u64, u64)>,
    /// Iterations at which the opacities were reset.
    pub opacity_resets: Vec<u64>,
    /// The run's last iteration (the x axis ends there).
    pub iterations: u64,
}

fn register_font() -> Result<()> {
    static DONE: OnceLock<bool> = OnceLock::new();
    let ok = *DONE.get_or_init(|| {
        plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular()).is_ok()
            && plotters::style::register_font(FONT, FontStyle::Bold, dejavu::sans::bold()).is_ok()
    });
    ok.then_some(()).ok_or_else(|| anyhow!("plot: the bundled DejaVu Sans font did not load"))
}

/// Writes `curves` to `path` as a PNG (atomically).
pub fn write(curves: &Curves, path: &Path) -> Result<()> {
    let png = render(curves)?;
    crate::util::write_atomic(path, |f| std::io::Write::write_all(f, &png))
}

/// The figure as PNG bytes.
pub fn render(c: &Curves) -> Result<Vec<u8>> {
    register_font()?;
    let e = |e: DrawingAreaErrorKind<_>| anyhow!("plot: {e}");
    let mut buf = vec![0u8; (WIDTH * HEIGHT * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (WIDTH, HEIGHT)).into_drawing_area();
        root.fill(&WHITE).map_err(e)?;
        let (top, body) = root.split_vertically(TITLE_HEIGHT);
        top.draw(&Text::new(
            c.title.clone(),
            (MARGIN as i32, 10),
            (FONT, 20).into_font().style(FontStyle::Bold).color(&BLACK),
        ))
        .map_err(e)?;
        let (left, right) = body.split_horizontally(WIDTH / 2);
        let x_max = c.iterations.max(1) as f64;

        // Loss on a log axis: whole decades around the data.
        let positive: Vec<(f64, f64)> =
            c.loss.iter().filter(|p| p.1 > 0.0 && p.1.is_finite()).map(|&(i, l)| (i as f64, l)).collect();
        let (lo, hi) = positive.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
        let (lo, hi) = if lo <= hi {
            (10f64.powf(lo.log10().floor()), 10f64.powf(hi.log10().ceil()).max(lo * 10.0))
        } else {
            (1e-3, 1.0)
        };
        // Ticks at 1, 2 and 5 of each decade.
        let ticks: Vec<f64> = (lo.log10().round() as i32..=hi.log10().round() as i32)
            .flat_map(|d| [1.0, 2.0, 5.0].map(|m| m * 10f64.powi(d)))
            .filter(|&v| v >= lo * 0.999 && v <= hi * 1.001)
            .collect();
        let y = (lo..hi).log_scale().with_key_points(ticks);
        let mut chart = panel::<WithKeyPoints<LogCoord<f64>>, _>(&left, "Training loss", x_max, y)?;
        axes(&mut chart, "loss, (1−λ)·L1 + λ·D-SSIM (log)", &|v| short(*v))?;
        schedule(&mut chart, c, lo, hi)?;
        chart
            .draw_series(LineSeries::new(positive, BLACK))
            .map_err(e)?
            .label("training loss")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 18, y)], BLACK));
        legend(&mut chart, SeriesLabelPosition::UpperRight)?;

        // PSNR: whole 5 dB steps around the data.
        let train: Vec<(f64, f64)> =
            c.train_psnr.iter().filter(|p| p.1.is_finite()).map(|&(i, p)| (i as f64, p)).collect();
        let test: Vec<(f64, f64)> =
            c.test_psnr.iter().filter(|p| p.1.is_finite()).map(|&(i, p)| (i as f64, p)).collect();
        let (plo, phi) = train.iter().chain(&test).fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
        let (plo, phi) =
            if plo <= phi { ((plo / 5.0).floor() * 5.0, (phi / 5.0).ceil() * 5.0 + 0.01) } else { (0.0, 40.0) };
        let mut chart = panel::<RangedCoordf64, _>(&right, "PSNR", x_max, plo..phi)?;
        axes(&mut chart, "PSNR (dB)", &|v| format!("{v:.0}"))?;
        schedule(&mut chart, c, plo, phi)?;
        let grey = RGBColor(160, 160, 160);
        chart
            .draw_series(LineSeries::new(train, grey))
            .map_err(e)?
            .label("training view of the iteration")
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], grey));
        if !test.is_empty() {
            chart.draw_series(LineSeries::new(test.clone(), RED.stroke_width(2))).map_err(e)?;
            chart
                .draw_series(test.iter().map(|&p| Circle::new(p, 4, RED.filled())))
                .map_err(e)?
                .label("held-out views (evaluations)")
                .legend(|(x, y)| Circle::new((x + 9, y), 4, RED.filled()));
        }
        legend(&mut chart, SeriesLabelPosition::LowerRight)?;
        root.present().map_err(e)?;
    }
    let img = image::RgbImage::from_raw(WIDTH, HEIGHT, buf).ok_or_else(|| anyhow!("plot: bad buffer"))?;
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)?;
    Ok(png)
}

type Area<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;
type Chart<'a, 'b, Y> = ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, Y>>;

fn panel<'a, 'b, Y: Ranged<ValueType = f64>, R: Into<Y>>(
    area: &'a Area<'b>,
    caption: &str,
    x_max: f64,
    y: R,
) -> Result<Chart<'a, 'b, Y>> {
    ChartBuilder::on(area)
        .caption(caption, (FONT, CAPTION).into_font().style(FontStyle::Bold))
        .margin(MARGIN)
        .x_label_area_size(X_LABEL_HEIGHT)
        .y_label_area_size(Y_LABEL_WIDTH)
        .build_cartesian_2d(0.0..x_max, y.into())
        .map_err(|e| anyhow!("plot: {e}"))
}

/// Numbered axes with their descriptions (iterations on x as 1k, 2k, …; `y_label` formats y).
fn axes<'a, 'b: 'a, Y>(chart: &mut Chart<'a, 'b, Y>, y_desc: &str, y_label: &dyn Fn(&f64) -> String) -> Result<()>
where
    Y: Ranged<ValueType = f64> + plotters::coord::ranged1d::ValueFormatter<f64>,
{
    chart
        .configure_mesh()
        .x_desc("iteration")
        .y_desc(y_desc)
        .y_labels(10)
        .x_labels(8)
        .max_light_lines(1)
        .y_label_formatter(y_label)
        .x_label_formatter(&|v| thousands(*v))
        .light_line_style(RGBColor(240, 240, 240))
        .bold_line_style(RGBColor(215, 215, 215))
        .label_style((FONT, 13))
        .axis_desc_style((FONT, 14))
        .draw()
        .map_err(|e| anyhow!("plot: {e}"))
}

/// The densification window (shaded) and the opacity resets (dashed), behind the data.
fn schedule<Y: Ranged<ValueType = f64>>(chart: &mut Chart<Y>, c: &Curves, y_lo: f64, y_hi: f64) -> Result<()> {
    let e = |e: DrawingAreaErrorKind<_>| anyhow!("plot: {e}");
    let x_max = c.iterations.max(1) as f64;
    if let Some((from, until)) = c.densify.filter(|d| (d.0 as f64) < x_max && d.0 < d.1) {
        let shade = RGBColor(200, 220, 255);
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(from as f64, y_lo), ((until as f64).min(x_max), y_hi)],
                shade.mix(0.5).filled(),
            )))
            .map_err(e)?
            .label("densification window")
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 18, y + 5)], shade.filled()));
    }
    let orange = RGBColor(230, 140, 0);
    let resets: Vec<f64> = c.opacity_resets.iter().map(|&i| i as f64).filter(|&i| i <= x_max).collect();
    for (k, &x) in resets.iter().enumerate() {
        let style = orange.stroke_width(2);
        let anno = chart.draw_series(DashedLineSeries::new([(x, y_lo), (x, y_hi)], 6, 4, style)).map_err(e)?;
        if k == 0 {
            anno.label("opacity reset")
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 7, y)], orange.stroke_width(2)));
        }
    }
    Ok(())
}

fn legend<'a, 'b: 'a, Y: Ranged<ValueType = f64>>(chart: &mut Chart<'a, 'b, Y>, at: SeriesLabelPosition) -> Result<()> {
    chart
        .configure_series_labels()
        .position(at)
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(180, 180, 180))
        .label_font((FONT, 13))
        .draw()
        .map_err(|e| anyhow!("plot: {e}"))
}

/// 12000 → "12k", 500 → "500".
fn thousands(v: f64) -> String {
    if v.abs() >= 1000.0 {
        let k = v / 1000.0;
        if (k - k.round()).abs() < 1e-9 {
            format!("{k:.0}k")
        } else {
            format!("{k:.1}k")
        }
    } else {
        format!("{v:.0}")
    }
}

/// A loss value with two significant digits (0.035, 0.1, 2).
fn short(v: f64) -> String {
    if v <= 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let digits = (1 - v.log10().floor() as i32).max(0) as usize;
    let s = format!("{v:.digits$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// `rate_distortion.png`: held-out PSNR against GPU memory for InstGS and the plain scene
/// pruned (one point per budget at InstGS's memory, and those of the equal-quality search; each
/// fine-tuned as long), and the plain scene whole.
#[derive(Clone, Debug, Default)]
pub struct RateDistortion {
    pub title: String,
    /// (MB, dB) per budget, by memory.
    pub instgs: Vec<(f64, f64)>,
    pub pruned: Vec<(f64, f64)>,
    pub plain: (f64, f64),
    /// InstGS's default budget (MB), marked.
    pub default_mb: Option<f64>,
}

/// Writes the memory–quality figure to `path` as a PNG (atomically).
pub fn write_rate_distortion(c: &RateDistortion, path: &Path) -> Result<()> {
    let png = render_rate_distortion(c)?;
    crate::util::write_atomic(path, |f| std::io::Write::write_all(f, &png))
}

/// The memory–quality figure as PNG bytes (900 × 560).
pub fn render_rate_distortion(c: &RateDistortion) -> Result<Vec<u8>> {
    register_font()?;
    let (w, h) = (900u32, 560u32);
    let e = |e: DrawingAreaErrorKind<_>| anyhow!("plot: {e}");
    let mut buf = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(e)?;
        let all: Vec<(f64, f64)> = c
            .instgs
            .iter()
            .chain(&c.pruned)
            .chain([&c.plain])
            .copied()
            .filter(|p| p.0.is_finite() && p.1.is_finite())
            .collect();
        let (x_hi, y_lo, y_hi) =
            all.iter().fold((0.0f64, f64::MAX, f64::MIN), |(x, a, b), p| (x.max(p.0), a.min(p.1), b.max(p.1)));
        let (y_lo, y_hi) = if y_lo <= y_hi { ((y_lo - 0.5).floor(), (y_hi + 0.5).ceil()) } else { (0.0, 40.0) };
        let mut chart = ChartBuilder::on(&root)
            .caption(c.title.clone(), (FONT, 17).into_font().style(FontStyle::Bold))
            .margin(MARGIN + 4)
            .x_label_area_size(X_LABEL_HEIGHT)
            .y_label_area_size(Y_LABEL_WIDTH)
            .build_cartesian_2d(0.0..(x_hi * 1.08).max(1e-3), y_lo..y_hi)
            .map_err(|e| anyhow!("plot: {e}"))?;
        chart
            .configure_mesh()
            .x_desc("GPU memory of the scene (MB)")
            .y_desc("held-out PSNR (dB)")
            .x_labels(10)
            .y_labels(10)
            .max_light_lines(1)
            .x_label_formatter(&|v| format!("{v:.1}"))
            .y_label_formatter(&|v| format!("{v:.1}"))
            .light_line_style(RGBColor(240, 240, 240))
            .bold_line_style(RGBColor(215, 215, 215))
            .label_style((FONT, 13))
            .axis_desc_style((FONT, 14))
            .draw()
            .map_err(|e| anyhow!("plot: {e}"))?;
        let blue = RGBColor(30, 90, 200);
        let grey = RGBColor(120, 120, 120);
        for (pts, colour, name) in
            [(&c.instgs, blue, "InstGS"), (&c.pruned, grey, "plain, pruned and fine-tuned as long")]
        {
            chart.draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2))).map_err(e)?;
            chart
                .draw_series(pts.iter().map(|&p| Circle::new(p, 5, colour.filled())))
                .map_err(e)?
                .label(name)
                .legend(move |(x, y)| Circle::new((x + 9, y), 5, colour.filled()));
        }
        chart
            .draw_series(std::iter::once(TriangleMarker::new(c.plain, 8, BLACK.filled())))
            .map_err(e)?
            .label("plain 3DGS")
            .legend(|(x, y)| TriangleMarker::new((x + 9, y), 7, BLACK.filled()));
        if let Some(d) = c.default_mb {
            let red = RGBColor(200, 40, 40);
            chart
                .draw_series(DashedLineSeries::new([(d, y_lo), (d, y_hi)], 6, 4, red.stroke_width(1)))
                .map_err(e)?
                .label("InstGS's default budget")
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], red));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(180, 180, 180))
            .label_font((FONT, 13))
            .draw()
            .map_err(|e| anyhow!("plot: {e}"))?;
        root.present().map_err(e)?;
    }
    let img = image::RgbImage::from_raw(w, h, buf).ok_or_else(|| anyhow!("plot: bad buffer"))?;
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)?;
    Ok(png)
}
