//! `v2ce render`: colours where known events fall (PNG, GIF) and frame counts (GIF, and MP4 by
//! ffprobe).

mod common;

use std::process::Command;

use v2ce::render::{BACKGROUND, OFF_COLOUR, ON_COLOUR};

fn v2ce() -> Command {
    Command::new(env!("CARGO_BIN_EXE_v2ce"))
}

fn close(a: &[u8], b: [u8; 3]) -> bool {
    a.iter()
        .zip(b)
        .all(|(&x, y)| (x as i32 - y as i32).abs() <= 12)
}

#[test]
fn renders_show_events_where_they_fall() {
    let dir = common::temp_dir("render");
    let csv = dir.join("ev.csv");
    // 16 x 8: ON at (3, 4), OFF at (10, 2), then 49 ms later ON at (5, 5).
    std::fs::write(&csv, "t_us,x,y,on\n1000,3,4,1\n2000,10,2,0\n50000,5,5,1\n").unwrap();
    let run = |out: &str, extra: &[&str]| {
        let o = v2ce()
            .arg("render")
            .arg(&csv)
            .arg("-o")
            .arg(dir.join(out))
            .args(["--size", "16x8"])
            .args(extra)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    run("all.png", &[]);
    // A file whose header claims a sensor past the frame limit is a clear error before the
    // canvas is allocated, not an abort (it was a 68 GB allocation).
    let huge = dir.join("huge.raw");
    std::fs::write(
        &huge,
        "% evt 3.0\n% format EVT3;height=65535;width=65535\n% end\n",
    )
    .unwrap();
    let o = v2ce()
        .arg("render")
        .arg(&huge)
        .arg("-o")
        .arg(dir.join("huge.png"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("8192"), "{err}");
    let png = image::open(dir.join("all.png")).unwrap().to_rgb8();
    assert_eq!(png.dimensions(), (16, 8));
    assert_eq!(png.get_pixel(3, 4).0, ON_COLOUR);
    assert_eq!(png.get_pixel(10, 2).0, OFF_COLOUR);
    assert_eq!(png.get_pixel(5, 5).0, ON_COLOUR);
    assert_eq!(png.get_pixel(0, 0).0, BACKGROUND);
    // 100 frames/s from the first event: windows ending at 11, 21, 31, 41 and 51 ms.
    run("ev.gif", &["--fps", "100"]);
    let file = std::fs::File::open(dir.join("ev.gif")).unwrap();
    let decoder = image::codecs::gif::GifDecoder::new(std::io::BufReader::new(file)).unwrap();
    let frames = image::AnimationDecoder::into_frames(decoder)
        .collect_frames()
        .unwrap();
    assert_eq!(frames.len(), 5);
    let first = frames[0].buffer();
    assert!(close(&first.get_pixel(3, 4).0[..3], ON_COLOUR));
    assert!(close(&first.get_pixel(10, 2).0[..3], OFF_COLOUR));
    assert!(close(&first.get_pixel(5, 5).0[..3], BACKGROUND), "not yet");
    let last = frames[4].buffer();
    assert!(close(&last.get_pixel(5, 5).0[..3], ON_COLOUR));
    assert!(
        close(&last.get_pixel(3, 4).0[..3], BACKGROUND),
        "a fixed window forgets"
    );
    // MP4 through ffmpeg: the same 5 frames, counted by ffprobe.
    if Command::new("ffprobe").arg("-version").output().is_err() {
        if std::env::var_os("CI").is_some() {
            panic!("ffprobe missing in CI");
        }
        skipped!("SKIPPED the MP4 part: no ffprobe (apt-get install ffmpeg)");
        return;
    }
    run("ev.mp4", &["--fps", "100"]);
    let probe = Command::new("ffprobe")
        .args(["-v", "error", "-count_frames", "-select_streams", "v:0"])
        .args(["-show_entries", "stream=nb_read_frames", "-of", "csv=p=0"])
        .arg(dir.join("ev.mp4"))
        .output()
        .unwrap();
    assert_eq!(String::from_utf8_lossy(&probe.stdout).trim(), "5");
}

#[test]
fn render_refuses_what_it_cannot_draw() {
    let dir = common::temp_dir("render-bad");
    let csv = dir.join("ev.csv");
    std::fs::write(&csv, "t_us,x,y,on\n1000,3,4,1\n").unwrap();
    for (args, needle) in [
        (vec!["-o", "x.png"], "--size"),
        (vec!["-o", "x.bmp", "--size", "4x4"], ".bmp"),
        (vec!["-o", "x.gif", "--size", "4x4", "--fps", "0"], "fps"),
    ] {
        let o = v2ce()
            .arg("render")
            .arg(&csv)
            .args(&args)
            .current_dir(&dir)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && err.contains(needle),
            "{args:?}: {err}"
        );
    }
}
