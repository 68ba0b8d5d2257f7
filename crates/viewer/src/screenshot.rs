//! Saving a frame as a PNG.

use std::io::BufWriter;
use std::path::Path;

/// Writes `pixels` (RGBA, rows top to bottom, `width × height` of them) as an 8-bit RGB
/// PNG. The framebuffer's alpha is whatever blending left there, so it is dropped.
pub fn write_png(path: &Path, width: u32, height: u32, pixels: &[[u8; 4]]) -> Result<(), String> {
    if pixels.len() != width as usize * height as usize {
        return Err(format!("{} pixels for a {width}×{height} image", pixels.len()));
    }
    let file = std::fs::File::create(path).map_err(|e| format!("creating {}: {e}", path.display()))?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().map_err(|e| format!("writing {}: {e}", path.display()))?;
    let rgb: Vec<u8> = pixels.iter().flat_map(|p| [p[0], p[1], p[2]]).collect();
    writer.write_image_data(&rgb).map_err(|e| format!("writing {}: {e}", path.display()))?;
    writer.finish().map_err(|e| format!("writing {}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.png");
        let pixels = [[255, 0, 0, 7], [0, 255, 0, 255], [0, 0, 255, 0], [9, 8, 7, 255], [1, 2, 3, 4], [4, 5, 6, 7]];
        write_png(&path, 3, 2, &pixels).unwrap();
        let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height, info.color_type), (3, 2, png::ColorType::Rgb));
        assert_eq!(&buf[..info.buffer_size()], &[255, 0, 0, 0, 255, 0, 0, 0, 255, 9, 8, 7, 1, 2, 3, 4, 5, 6]);
        assert!(write_png(&path, 4, 2, &pixels).is_err());
    }
}
