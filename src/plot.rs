//! `curves.png`: training curves drawn with plotters (bitmap backend, no text: the build has no
//! font). Left panel: the training loss (log10, black) per iteration; right panel: PSNR in dB,
//! training (grey, per iteration) and test views (red). Horizontal grid lines every 0.5 decade
//! of loss and every 5 dB; vertical ones every tenth of the run.
use std::path::Path;

use anyhow::{anyhow, Result};
use plotters::prelude::*;

use crate::train::MetricsRow;

pub fn curves(rows: &[MetricsRow], path: &Path) -> Result<()> {
    let (w, h) = (1000u32, 400u32);
    let mut buf = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow!("plot: {e}"))?;
        let (left, right) = root.split_horizontally(w / 2);
        let last = rows.last().map_or(1, |r| r.iteration).max(1) as f64;
        let log_loss: Vec<(f64, f64)> =
            rows.iter().filter(|r| r.loss > 0.0).map(|r| (r.iteration as f64, r.loss.log10())).collect();
        let (lo, hi) = log_loss.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
        let (lo, hi) = if lo <= hi { ((lo * 2.0).floor() / 2.0, (hi * 2.0).ceil() / 2.0 + 0.01) } else { (-3.0, 0.0) };
        panel(&left, last, lo, hi, 0.5, &[(log_loss, BLACK)])?;
        let train: Vec<(f64, f64)> =
            rows.iter().filter(|r| r.train_psnr.is_finite()).map(|r| (r.iteration as f64, r.train_psnr)).collect();
        let test: Vec<(f64, f64)> = rows.iter().filter_map(|r| r.test_psnr.map(|p| (r.iteration as f64, p))).collect();
        let all = train.iter().chain(&test);
        let (plo, phi) = all.fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
        let (plo, phi) =
            if plo <= phi { ((plo / 5.0).floor() * 5.0, (phi / 5.0).ceil() * 5.0 + 0.01) } else { (0.0, 40.0) };
        panel(&right, last, plo, phi, 5.0, &[(train, RGBColor(170, 170, 170)), (test, RED)])?;
        root.present().map_err(|e| anyhow!("plot: {e}"))?;
    }
    let img = image::RgbImage::from_raw(w, h, buf).ok_or_else(|| anyhow!("plot: bad buffer"))?;
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)?;
    crate::util::write_atomic(path, |f| std::io::Write::write_all(f, &png))
}

type Area<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;

fn panel(
    area: &Area,
    x_max: f64,
    y_lo: f64,
    y_hi: f64,
    y_step: f64,
    series: &[(Vec<(f64, f64)>, RGBColor)],
) -> Result<()> {
    let e = |e: DrawingAreaErrorKind<_>| anyhow!("plot: {e}");
    let area = area.margin(12, 12, 12, 12);
    let mut chart = ChartBuilder::on(&area).build_cartesian_2d(0.0..x_max, y_lo..y_hi).map_err(e)?;
    let grid = RGBColor(225, 225, 225);
    let mut y = (y_lo / y_step).ceil() * y_step;
    while y < y_hi {
        chart.draw_series(LineSeries::new([(0.0, y), (x_max, y)], grid)).map_err(e)?;
        y += y_step;
    }
    for i in 1..10 {
        let x = x_max * i as f64 / 10.0;
        chart.draw_series(LineSeries::new([(x, y_lo), (x, y_hi)], grid)).map_err(e)?;
    }
    chart
        .draw_series(LineSeries::new([(0.0, y_lo), (x_max, y_lo), (x_max, y_hi), (0.0, y_hi), (0.0, y_lo)], BLACK))
        .map_err(e)?;
    for (points, color) in series {
        chart.draw_series(LineSeries::new(points.iter().copied(), *color)).map_err(e)?;
    }
    Ok(())
}
