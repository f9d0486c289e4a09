//! The player's overlay: text (frame rate, GPU time, splat count, the editor's selection and
//! keys) in a 5×7 bitmap font drawn on the CPU into a small RGBA8 image that `present.comp`
//! blends over the frame's top-left corner, redrawn a few times per second; with an instance
//! selected, a frame-sized image that also holds the selection's box outline.

/// Glyph rows, `#` = ink, 5 columns × 7 rows. Characters without a glyph are drawn blank.
const FONT: &[(char, [&str; 7])] = &[
    ('0', [".###.", "#...#", "#..##", "#.#.#", "##..#", "#...#", ".###."]),
    ('1', ["..#..", ".##..", "..#..", "..#..", "..#..", "..#..", ".###."]),
    ('2', [".###.", "#...#", "....#", "...#.", "..#..", ".#...", "#####"]),
    ('3', ["#####", "...#.", "..#..", "...#.", "....#", "#...#", ".###."]),
    ('4', ["...#.", "..##.", ".#.#.", "#..#.", "#####", "...#.", "...#."]),
    ('5', ["#####", "#....", "####.", "....#", "....#", "#...#", ".###."]),
    ('6', ["..##.", ".#...", "#....", "####.", "#...#", "#...#", ".###."]),
    ('7', ["#####", "....#", "...#.", "..#..", ".#...", ".#...", ".#..."]),
    ('8', [".###.", "#...#", "#...#", ".###.", "#...#", "#...#", ".###."]),
    ('9', [".###.", "#...#", "#...#", ".####", "....#", "...#.", ".##.."]),
    ('.', [".....", ".....", ".....", ".....", ".....", ".##..", ".##.."]),
    (',', [".....", ".....", ".....", ".....", ".##..", "..#..", ".#..."]),
    ('?', [".###.", "#...#", "....#", "...#.", "..#..", ".....", "..#.."]),
    ('!', ["..#..", "..#..", "..#..", "..#..", "..#..", ".....", "..#.."]),
    ('\'', ["..#..", "..#..", ".#...", ".....", ".....", ".....", "....."]),
    ('(', ["...#.", "..#..", ".#...", ".#...", ".#...", "..#..", "...#."]),
    (')', [".#...", "..#..", "...#.", "...#.", "...#.", "..#..", ".#..."]),
    ('[', [".###.", ".#...", ".#...", ".#...", ".#...", ".#...", ".###."]),
    (']', [".###.", "...#.", "...#.", "...#.", "...#.", "...#.", ".###."]),
    ('+', [".....", "..#..", "..#..", "#####", "..#..", "..#..", "....."]),
    ('=', [".....", ".....", "#####", ".....", "#####", ".....", "....."]),
    ('°', [".##..", "#..#.", ".##..", ".....", ".....", ".....", "....."]),
    ('_', [".....", ".....", ".....", ".....", ".....", ".....", "#####"]),
    (':', [".....", ".##..", ".##..", ".....", ".##..", ".##..", "....."]),
    ('-', [".....", ".....", ".....", "#####", ".....", ".....", "....."]),
    ('/', ["....#", "....#", "...#.", "..#..", ".#...", "#....", "#...."]),
    ('|', ["..#..", "..#..", "..#..", "..#..", "..#..", "..#..", "..#.."]),
    ('A', [".###.", "#...#", "#...#", "#####", "#...#", "#...#", "#...#"]),
    ('B', ["####.", "#...#", "#...#", "####.", "#...#", "#...#", "####."]),
    ('C', [".###.", "#...#", "#....", "#....", "#....", "#...#", ".###."]),
    ('D', ["####.", "#...#", "#...#", "#...#", "#...#", "#...#", "####."]),
    ('E', ["#####", "#....", "#....", "####.", "#....", "#....", "#####"]),
    ('F', ["#####", "#....", "#....", "####.", "#....", "#....", "#...."]),
    ('G', [".###.", "#...#", "#....", "#.###", "#...#", "#...#", ".####"]),
    ('H', ["#...#", "#...#", "#...#", "#####", "#...#", "#...#", "#...#"]),
    ('I', [".###.", "..#..", "..#..", "..#..", "..#..", "..#..", ".###."]),
    ('J', ["..###", "...#.", "...#.", "...#.", "...#.", "#..#.", ".##.."]),
    ('K', ["#...#", "#..#.", "#.#..", "##...", "#.#..", "#..#.", "#...#"]),
    ('L', ["#....", "#....", "#....", "#....", "#....", "#....", "#####"]),
    ('M', ["#...#", "##.##", "#.#.#", "#.#.#", "#...#", "#...#", "#...#"]),
    ('N', ["#...#", "#...#", "##..#", "#.#.#", "#..##", "#...#", "#...#"]),
    ('O', [".###.", "#...#", "#...#", "#...#", "#...#", "#...#", ".###."]),
    ('P', ["####.", "#...#", "#...#", "####.", "#....", "#....", "#...."]),
    ('Q', [".###.", "#...#", "#...#", "#...#", "#.#.#", "#..#.", ".##.#"]),
    ('R', ["####.", "#...#", "#...#", "####.", "#.#..", "#..#.", "#...#"]),
    ('S', [".####", "#....", "#....", ".###.", "....#", "....#", "####."]),
    ('T', ["#####", "..#..", "..#..", "..#..", "..#..", "..#..", "..#.."]),
    ('U', ["#...#", "#...#", "#...#", "#...#", "#...#", "#...#", ".###."]),
    ('V', ["#...#", "#...#", "#...#", "#...#", "#...#", ".#.#.", "..#.."]),
    ('W', ["#...#", "#...#", "#...#", "#.#.#", "#.#.#", "#.#.#", ".#.#."]),
    ('X', ["#...#", "#...#", ".#.#.", "..#..", ".#.#.", "#...#", "#...#"]),
    ('Y', ["#...#", "#...#", ".#.#.", "..#..", "..#..", "..#..", "..#.."]),
    ('Z', ["#####", "....#", "...#.", "..#..", ".#...", "#....", "#####"]),
];

/// Pixels per font pixel.
const SCALE: u32 = 2;
/// Margin around the text, in pixels.
const MARGIN: u32 = 6;
const CELL_W: u32 = 6 * SCALE;
const CELL_H: u32 = 9 * SCALE;

/// An RGBA8 image (packed little-endian `r | g << 8 | b << 16 | a << 24`, straight alpha).
#[derive(Clone)]
pub struct Overlay {
    pub width: u32,
    pub height: u32,
    pub texels: Vec<u32>,
}

fn pack(rgba: [u8; 4]) -> u32 {
    u32::from_le_bytes(rgba)
}

/// Draws `lines` (upper-cased) in white on a translucent black box.
pub fn draw(lines: &[String]) -> Overlay {
    let cols = lines.iter().map(|l| l.chars().count()).max().unwrap_or(0) as u32;
    let width = cols * CELL_W + 2 * MARGIN;
    let height = lines.len() as u32 * CELL_H + 2 * MARGIN;
    let mut texels = vec![pack([0, 0, 0, 150]); (width * height) as usize];
    for (row, line) in lines.iter().enumerate() {
        for (col, ch) in line.to_uppercase().chars().enumerate() {
            let Some((_, glyph)) = FONT.iter().find(|g| g.0 == ch) else { continue };
            let (x0, y0) = (MARGIN + col as u32 * CELL_W, MARGIN + row as u32 * CELL_H + SCALE);
            for (gy, bits) in glyph.iter().enumerate() {
                for (gx, b) in bits.bytes().enumerate() {
                    if b != b'#' {
                        continue;
                    }
                    for dy in 0..SCALE {
                        for dx in 0..SCALE {
                            let (x, y) = (x0 + gx as u32 * SCALE + dx, y0 + gy as u32 * SCALE + dy);
                            texels[(y * width + x) as usize] = pack([255, 255, 255, 255]);
                        }
                    }
                }
            }
        }
    }
    Overlay { width, height, texels }
}

/// The part of segment a–b inside [0, w] × [0, h] (Liang–Barsky), if any.
fn clip(a: [f32; 2], b: [f32; 2], w: f32, h: f32) -> Option<([f32; 2], [f32; 2])> {
    let d = [b[0] - a[0], b[1] - a[1]];
    let (mut t0, mut t1) = (0.0f32, 1.0f32);
    for (p, q) in [(-d[0], a[0]), (d[0], w - a[0]), (-d[1], a[1]), (d[1], h - a[1])] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else if p < 0.0 {
            t0 = t0.max(q / p);
        } else {
            t1 = t1.min(q / p);
        }
    }
    (t0 <= t1 && t0.is_finite() && t1.is_finite())
        .then(|| ([a[0] + t0 * d[0], a[1] + t0 * d[1]], [a[0] + t1 * d[0], a[1] + t1 * d[1]]))
}

/// A `width` × `height` overlay: transparent, `text` in the top-left corner, `lines` (pixel
/// end points, clipped to the frame) drawn one pixel wide in `colour`.
pub fn frame(
    width: u32,
    height: u32,
    text: Option<&Overlay>,
    lines: &[([f32; 2], [f32; 2])],
    colour: [u8; 4],
) -> Overlay {
    let mut texels = vec![0u32; (width * height) as usize];
    for &(a, b) in lines {
        let Some((a, b)) = clip(a, b, width as f32, height as f32) else { continue };
        let steps = (b[0] - a[0]).abs().max((b[1] - a[1]).abs()).ceil().max(1.0) as u32;
        for i in 0..=steps {
            let f = i as f32 / steps as f32;
            let (x, y) = ((a[0] + (b[0] - a[0]) * f).round(), (a[1] + (b[1] - a[1]) * f).round());
            if x >= 0.0 && y >= 0.0 && (x as u32) < width && (y as u32) < height {
                texels[(y as u32 * width + x as u32) as usize] = pack(colour);
            }
        }
    }
    if let Some(t) = text {
        for y in 0..t.height.min(height) {
            for x in 0..t.width.min(width) {
                texels[(y * width + x) as usize] = t.texels[(y * t.width + x) as usize];
            }
        }
    }
    Overlay { width, height, texels }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glyphs_are_5_by_7_and_unique() {
        for (i, (c, rows)) in FONT.iter().enumerate() {
            assert!(rows.iter().all(|r| r.len() == 5 && r.bytes().all(|b| b == b'#' || b == b'.')), "{c}");
            assert!(FONT[i + 1..].iter().all(|g| g.0 != *c && g.1 != *rows), "{c}");
        }
    }

    #[test]
    fn text_is_drawn_inside_its_box() {
        let o = draw(&["123.4 FPS".into(), "gpu 8.1 ms".into()]);
        assert_eq!((o.width, o.height), (10 * CELL_W + 2 * MARGIN, 2 * CELL_H + 2 * MARGIN));
        let ink = o.texels.iter().filter(|&&t| t == pack([255; 4])).count();
        assert!(ink > 0);
        // The margin stays background.
        assert!((0..o.width).all(|x| o.texels[x as usize] == pack([0, 0, 0, 150])));
    }

    #[test]
    fn frame_overlay_clips_lines_and_keeps_the_text() {
        let text = draw(&["ab".into()]);
        let o = frame(
            100,
            60,
            Some(&text),
            &[([-50.0, 30.0], [150.0, 30.0]), ([5.0, -1e9], [5.0, 1e9])],
            [255, 255, 0, 255],
        );
        let yellow = pack([255, 255, 0, 255]);
        assert!((text.width..100).all(|x| o.texels[(30 * 100 + x) as usize] == yellow));
        assert!((text.height..60).all(|y| o.texels[(y * 100 + 5) as usize] == yellow));
        assert_eq!(o.texels[(59 * 100 + 50) as usize], 0, "untouched texels stay transparent");
        assert_eq!(o.texels[0], text.texels[0]);
    }
}
