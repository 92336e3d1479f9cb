//! Image files of a render: OpenEXR (one channel per colour and a
//! standard-error channel each), PNG previews and `.npy` arrays. Every write
//! is atomic (temporary sibling + rename, [`crate::jobs::store`]).
//!
//! # Tone map of the PNG previews (stated, shared by all methods of a scene)
//! v ↦ sRGB-OETF(clamp(v/white, 0, 1)) in 8 bits, with `white` the 99.5th
//! percentile of the *reference* image (or, when the pass has no reference,
//! of its first rendered image), so that every method of a scene is shown
//! on one scale.
//! Signed differences use a diverging map (blue − / white 0 / red +) with
//! full scale ±`range`.

use crate::error::{Error, Result};
use crate::jobs::store::{write_atomic, write_npy_atomic};
use crate::render::estimator::Image;
use std::path::Path;

/// Channel names of an image with `c` channels.
fn names(c: usize) -> Vec<&'static str> {
    match c {
        1 => vec!["Y"],
        _ => vec!["R", "G", "B"],
    }
}

/// Writes `img` as a one-layer OpenEXR with channels Y (or R, G, B) and
/// stderr.Y (or stderr.R, …), 32-bit float, row 0 at the top (+y).
pub fn write_exr(path: &Path, img: &Image, layer: &str) -> Result<()> {
    use exr::prelude::*;
    let n = img.resolution;
    let plane = |v: &[f64], c: usize| -> Vec<f32> {
        v[c * n * n..(c + 1) * n * n]
            .iter()
            .map(|x| *x as f32)
            .collect()
    };
    let mut channels = Vec::new();
    for (c, name) in names(img.channels).into_iter().enumerate() {
        channels.push(AnyChannel::new(name, FlatSamples::F32(plane(&img.mean, c))));
        channels.push(AnyChannel::new(
            format!("stderr.{name}").as_str(),
            FlatSamples::F32(plane(&img.stderr, c)),
        ));
    }
    let layer = Layer::new(
        (n, n),
        LayerAttributes::named(layer),
        Encoding::FAST_LOSSLESS,
        AnyChannels::sort(SmallVec::from_vec(channels)),
    );
    let mut bytes = std::io::Cursor::new(Vec::new());
    exr::prelude::Image::from_layer(layer)
        .write()
        .to_buffered(&mut bytes)
        .map_err(|e| crate::Error::format(path, "(exr)", e))?;
    write_atomic(path, bytes.get_ref())
}

/// Writes the mean and the standard error as `(N, N, C)` `.npy` arrays.
pub fn write_npy(mean_path: &Path, stderr_path: &Path, img: &Image) -> Result<()> {
    let n = img.resolution;
    let arr = |v: &[f64]| {
        ndarray::Array3::from_shape_fn((n, n, img.channels), |(i, j, c)| v[img.index(c, i, j)])
    };
    write_npy_atomic(mean_path, &arr(&img.mean))?;
    write_npy_atomic(stderr_path, &arr(&img.stderr))
}

/// The white point of the previews: the 99.5th percentile of `img`'s values
/// (at least the smallest positive f64).
pub fn white_point(img: &Image) -> f64 {
    let mut v: Vec<f64> = img.mean.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return 1.0;
    }
    v.sort_by(f64::total_cmp);
    let k = ((v.len() - 1) as f64 * 0.995).round() as usize;
    v[k].max(f64::MIN_POSITIVE)
}

/// sRGB opto-electronic transfer function (IEC 61966-2-1).
#[inline]
pub(crate) fn srgb(x: f64) -> f64 {
    if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}

pub(crate) fn to_u8(x: f64) -> u8 {
    (x.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Encodes an n × n image of 8-bit pixels (1 or 3 bytes each) as PNG and
/// writes atomically.
pub fn write_png_bytes(path: &Path, n: usize, rgb: bool, data: &[u8]) -> Result<()> {
    write_png_bytes_wh(path, n, n, rgb, data)
}

/// [`write_png_bytes`] for a `width × height` image.
pub fn write_png_bytes_wh(
    path: &Path,
    width: usize,
    height: usize,
    rgb: bool,
    data: &[u8],
) -> Result<()> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, width as u32, height as u32);
        enc.set_color(if rgb {
            png::ColorType::Rgb
        } else {
            png::ColorType::Grayscale
        });
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc
            .write_header()
            .map_err(|e| Error::format(path, "(png)", e))?;
        w.write_image_data(data)
            .map_err(|e| Error::format(path, "(png)", e))?;
    }
    write_atomic(path, &out)
}

/// The tone-mapped preview of `img` (module docs).
pub fn write_png(path: &Path, img: &Image, white: f64) -> Result<()> {
    let n = img.resolution;
    let mut data = Vec::with_capacity(n * n * img.channels);
    for i in 0..n {
        for j in 0..n {
            data.extend((0..img.channels).map(|c| tone(img, c, i, j, white)));
        }
    }
    write_png_bytes(path, n, img.channels == 3, &data)
}

/// The preview byte of channel c of pixel (i, j) (module docs).
#[inline]
fn tone(img: &Image, c: usize, i: usize, j: usize, white: f64) -> u8 {
    to_u8(srgb(img.mean[img.index(c, i, j)] / white))
}

/// The diverging colour of the channel-mean difference a − b at pixel
/// (i, j), full scale ±`range`.
#[inline]
fn difference(a: &Image, b: &Image, i: usize, j: usize, range: f64) -> [u8; 3] {
    let d = (0..a.channels)
        .map(|c| a.mean[a.index(c, i, j)] - b.mean[b.index(c, i, j)])
        .sum::<f64>()
        / a.channels as f64;
    diverging((d / range).clamp(-1.0, 1.0))
}

/// A diverging preview of the signed difference `a − b` (channel mean),
/// full scale ±`range`.
pub fn write_diff_png(path: &Path, a: &Image, b: &Image, range: f64) -> Result<()> {
    let n = a.resolution;
    let mut data = Vec::with_capacity(n * n * 3);
    for i in 0..n {
        for j in 0..n {
            data.extend(difference(a, b, i, j, range));
        }
    }
    write_png_bytes(path, n, true, &data)
}

/// A contact sheet in the seed's style: the images side by side (top row,
/// tone-mapped with `white`) and, below each model image, its signed
/// difference to `images[0]` (the reference) at full scale ±`range`; tiles
/// enlarged by pixel replication to ≥ 128 px, 4 px white gaps. RGB PNG.
pub fn write_row_png(path: &Path, images: &[&Image], white: f64, range: f64) -> Result<()> {
    let n = images.first().map_or(1, |i| i.resolution);
    let zoom = 128usize.div_ceil(n).max(1);
    let (tile, gap) = (n * zoom, 4);
    let width = images.len() * (tile + gap) - gap;
    let height = 2 * tile + gap;
    let mut data = vec![255u8; width * height * 3];
    // Paints the zoom × zoom block of source pixel (i, j) at tile origin (x0, y0).
    let mut block = |x0: usize, y0: usize, i: usize, j: usize, rgb: [u8; 3]| {
        for y in y0 + i * zoom..y0 + (i + 1) * zoom {
            for x in x0 + j * zoom..x0 + (j + 1) * zoom {
                let k = 3 * (y * width + x);
                data[k..k + 3].copy_from_slice(&rgb);
            }
        }
    };
    for (t, img) in images.iter().enumerate() {
        let x0 = t * (tile + gap);
        for i in 0..n {
            for j in 0..n {
                let rgb = std::array::from_fn(|c| tone(img, c.min(img.channels - 1), i, j, white));
                block(x0, 0, i, j, rgb);
                if t > 0 {
                    block(
                        x0,
                        tile + gap,
                        i,
                        j,
                        difference(img, images[0], i, j, range),
                    );
                }
            }
        }
    }
    write_png_bytes_wh(path, width, height, true, &data)
}

/// A preview of input maps over the image window (half-width `half_width`,
/// as the renders see them): one map is grey, three are R, G, B; each texel
/// value v is shown as v / `white` in linear 8-bit (black 0, white
/// `white`), nearest texel at each preview pixel's centre. The preview has
/// `n` pixels a side, raised to the texel count across the window (at most
/// 4n) so that texels smaller than a render pixel still show.
pub fn write_map_png(
    path: &Path,
    maps: &[&crate::forward::maps::TexelMap],
    n: usize,
    half_width: f64,
    white: f64,
) -> Result<()> {
    let texel = maps.iter().map(|m| m.texel).fold(f64::INFINITY, f64::min);
    let across = (2.0 * half_width / texel).ceil();
    let m = if across.is_finite() {
        (across as usize).clamp(n, 4 * n)
    } else {
        n
    };
    let step = 2.0 * half_width / m as f64;
    let mut data = Vec::with_capacity(m * m * maps.len());
    for i in 0..m {
        let y = half_width - (i as f64 + 0.5) * step;
        for j in 0..m {
            let x = -half_width + (j as f64 + 0.5) * step;
            data.extend(maps.iter().map(|map| to_u8(map.at(x, y) / white)));
        }
    }
    write_png_bytes(path, m, maps.len() == 3, &data)
}

/// The colour bar of the difference images: [`diverging`] from −1 (left)
/// to +1 (right), `width` × `height` pixels.
pub fn write_colorbar(path: &Path, width: usize, height: usize) -> Result<()> {
    let row: Vec<u8> = (0..width)
        .flat_map(|x| diverging(2.0 * (x as f64 + 0.5) / width as f64 - 1.0))
        .collect();
    write_png_bytes_wh(path, width, height, true, &row.repeat(height))
}

/// Blue (−1) → white (0) → red (+1), in sRGB bytes.
pub fn diverging(t: f64) -> [u8; 3] {
    let (r, g, b) = if t < 0.0 {
        (1.0 + t, 1.0 + t, 1.0)
    } else {
        (1.0, 1.0 - t, 1.0 - t)
    };
    [to_u8(srgb(r)), to_u8(srgb(g)), to_u8(srgb(b))]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exr_and_png_round_trip_shapes() {
        let dir = std::env::temp_dir().join(format!("svk-out-{}", std::process::id()));
        let mut img = crate::render::estimator::Image::zeros(4, 3);
        for (k, v) in img.mean.iter_mut().enumerate() {
            *v = k as f64 * 0.01;
        }
        write_exr(&dir.join("a.exr"), &img, "test").unwrap();
        write_png(&dir.join("a.png"), &img, white_point(&img)).unwrap();
        write_npy(&dir.join("m.npy"), &dir.join("e.npy"), &img).unwrap();
        use exr::prelude::{Vec2, read_all_flat_layers_from_file};
        let back = read_all_flat_layers_from_file(dir.join("a.exr")).unwrap();
        let layer = &back.layer_data[0];
        assert_eq!(layer.size, Vec2(4, 4));
        assert_eq!(layer.channel_data.list.len(), 6);
        // Channels are sorted by name: B, G, R, stderr.B, …; R at (row 0, col 1).
        let r = &layer.channel_data.list[2];
        assert_eq!(r.name.to_string(), "R");
        assert_eq!(r.sample_data.value_by_flat_index(1).to_f32(), 0.01);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
