//! The player's text overlay (frame rate, GPU time, splat count): a 5×7 bitmap font drawn on
//! the CPU into a small RGBA8 image that `present.comp` blends over the frame's top-left corner.
//! Redrawn a few times per second, so its cost never shows in the frame time.

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
    ('K', ["#...#", "#..#.", "#.#..", "##...", "#.#..", "#..#.", "#...#"]),
    ('L', ["#....", "#....", "#....", "#....", "#....", "#....", "#####"]),
    ('M', ["#...#", "##.##", "#.#.#", "#.#.#", "#...#", "#...#", "#...#"]),
    ('N', ["#...#", "#...#", "##..#", "#.#.#", "#..##", "#...#", "#...#"]),
    ('O', [".###.", "#...#", "#...#", "#...#", "#...#", "#...#", ".###."]),
    ('P', ["####.", "#...#", "#...#", "####.", "#....", "#....", "#...."]),
    ('R', ["####.", "#...#", "#...#", "####.", "#.#..", "#..#.", "#...#"]),
    ('S', [".####", "#....", "#....", ".###.", "....#", "....#", "####."]),
    ('T', ["#####", "..#..", "..#..", "..#..", "..#..", "..#..", "..#.."]),
    ('U', ["#...#", "#...#", "#...#", "#...#", "#...#", "#...#", ".###."]),
    ('V', ["#...#", "#...#", "#...#", "#...#", "#...#", ".#.#.", "..#.."]),
    ('W', ["#...#", "#...#", "#...#", "#.#.#", "#.#.#", "#.#.#", ".#.#."]),
    ('X', ["#...#", "#...#", ".#.#.", "..#..", ".#.#.", "#...#", "#...#"]),
    ('Y', ["#...#", "#...#", ".#.#.", "..#..", "..#..", "..#..", "..#.."]),
];

/// Pixels per font pixel.
const SCALE: u32 = 2;
/// Margin around the text, in pixels.
const MARGIN: u32 = 6;
const CELL_W: u32 = 6 * SCALE;
const CELL_H: u32 = 9 * SCALE;

/// An RGBA8 image (packed little-endian `r | g << 8 | b << 16 | a << 24`, straight alpha).
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
}
