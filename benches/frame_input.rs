//! Frame input at memory speed (issue 27): decoding the bundled fixture (Y4M, monochrome,
//! 640 x 480, 180 frames, Zstandard-compressed) to the model's linear luminance, frames per
//! second of one thread, median of 5 passes; and an 8-bit camera frame (GREY) converted the
//! same way. `cargo bench --bench frame_input`.

use std::time::Instant;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let mut rates = Vec::new();
    let mut frames = 0;
    for _ in 0..5 {
        let mut source = match v2ce::frame::fixture::open() {
            Ok(s) => s,
            Err(e) => {
                eprintln!("SKIPPED: the fixture does not open: {e}");
                return;
            }
        };
        let start = Instant::now();
        frames = 0;
        while let Ok(Some(_)) = source.next_frame() {
            frames += 1;
        }
        rates.push(frames as f64 / start.elapsed().as_secs_f64());
    }
    println!(
        "fixture (Y4M mono 640x480, {frames} frames, zstd): {:.0} frames/s",
        median(rates)
    );
    let gray: Vec<u8> = (0..640 * 480).map(|i| (i * 7 % 251) as u8).collect();
    let mut rates = Vec::new();
    for _ in 0..5 {
        let start = Instant::now();
        let mut sum = 0u64;
        for _ in 0..200 {
            let luma: Vec<u16> = gray
                .iter()
                .map(|&v| v2ce::frame::color::gray_to_luma(v))
                .collect();
            sum += u64::from(luma[luma.len() / 2]);
        }
        std::hint::black_box(sum);
        rates.push(200.0 / start.elapsed().as_secs_f64());
    }
    println!("GREY 640x480 to luminance: {:.0} frames/s", median(rates));
}
