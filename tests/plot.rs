//! `curves.png` is a figure a reader can use: text (title, tick numbers, axis labels) is drawn
//! in the title band and in each panel's axis areas, not only lines.
use instgs_vk::train::plot::{self, Curves, HEIGHT, TITLE_HEIGHT, WIDTH, X_LABEL_HEIGHT, Y_LABEL_WIDTH};

fn synthetic_run() -> Curves {
    let n = 3000u64;
    let loss =
        (1..=n).map(|i| (i, 0.2 * (-(i as f64) / 800.0).exp() + 0.02 + 0.005 * ((i as f64) * 0.7).sin())).collect();
    let train_psnr =
        (1..=n).map(|i| (i, 14.0 + 16.0 * (1.0 - (-(i as f64) / 700.0).exp()) + ((i as f64) * 1.3).sin())).collect();
    let test_psnr = (1..=6).map(|k| (k * 500, 15.0 + 2.5 * k as f64)).collect();
    Curves {
        title: "Plain 3DGS training: 3000 iterations, 20 training views, 5 held-out views".into(),
        loss,
        train_psnr,
        test_psnr,
        densify: Some((500, 2500)),
        opacity_resets: vec![1000, 2000],
        iterations: n,
    }
}

/// Pixels of anti-aliased text: grey levels strictly between ink and paper. Lines and fills in
/// the figure are drawn without anti-aliasing in saturated or light colours, so only glyph
/// edges give neutral mid greys.
fn text_pixels(img: &image::RgbImage, x0: u32, x1: u32, y0: u32, y1: u32) -> usize {
    let mut n = 0;
    for y in y0..y1 {
        for x in x0..x1 {
            let [r, g, b] = img.get_pixel(x, y).0;
            let neutral = r.abs_diff(g) <= 2 && g.abs_diff(b) <= 2;
            if neutral && (30..=200).contains(&r) {
                n += 1;
            }
        }
    }
    n
}

#[test]
fn the_training_figure_has_text_in_its_axes() {
    let png = plot::render(&synthetic_run()).unwrap();
    let img = image::load_from_memory(&png).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (WIDTH, HEIGHT));
    if let Ok(dir) = std::env::var("INSTGS_PLOT_OUT") {
        std::fs::write(std::path::Path::new(&dir).join("curves.png"), &png).unwrap();
    }
    let title = text_pixels(&img, 0, WIDTH, 0, TITLE_HEIGHT);
    assert!(title > 200, "the title band holds {title} text pixels");
    for (name, x0) in [("loss", 0), ("PSNR", WIDTH / 2)] {
        // Below the plot: the x tick numbers and "iteration".
        let x_axis = text_pixels(&img, x0 + Y_LABEL_WIDTH, x0 + WIDTH / 2, HEIGHT - X_LABEL_HEIGHT, HEIGHT);
        // Left of the plot: the y tick numbers and the axis description.
        let y_axis = text_pixels(&img, x0, x0 + Y_LABEL_WIDTH, TITLE_HEIGHT + 40, HEIGHT - X_LABEL_HEIGHT);
        assert!(x_axis > 150, "{name} panel: {x_axis} text pixels under the x axis");
        assert!(y_axis > 150, "{name} panel: {y_axis} text pixels left of the y axis");
    }
}

#[test]
fn an_empty_run_still_draws_a_figure() {
    let png = plot::render(&Curves { title: "no iterations".into(), ..Curves::default() }).unwrap();
    assert!(image::load_from_memory(&png).is_ok());
}
