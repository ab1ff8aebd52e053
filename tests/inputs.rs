//! Frame inputs without traps: a frame list is a source wherever a folder is, a DAVIS APS
//! export is read as linear light (and gray images of unknown colour space are warned about),
//! and a text file is never handed to ffmpeg as a video.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use v2ce::event::Event;

fn v2ce() -> Command {
    Command::new(env!("CARGO_BIN_EXE_v2ce"))
}

fn convert(input: &Path, out: &Path, extra: &[&str]) -> Output {
    v2ce()
        .arg("convert")
        .arg(input)
        .arg("-o")
        .arg(out)
        .args(["--force", "--seed", "3"])
        .args(extra)
        .output()
        .unwrap()
}

fn ok(out: &Output) -> String {
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(out.status.success(), "{stderr}");
    stderr
}

fn events(path: &Path) -> Vec<Event> {
    v2ce::format::read_events(path)
        .unwrap()
        .events
        .events()
        .to_vec()
}

/// Writes 8 gray 8-bit PNGs of a bright bar moving right into `dir/images/`, and an IJRR
/// `images.txt` (25 Hz, mid-exposure times) listing them; with `events_txt`, an `events.txt`
/// beside it as a DAVIS export has.
fn export(dir: &Path, events_txt: bool) -> PathBuf {
    std::fs::create_dir_all(dir.join("images")).unwrap();
    let mut list = String::new();
    for k in 0..8u32 {
        let img = image::GrayImage::from_fn(48, 32, |x, _| {
            let d = (x as i32 - 8 - 4 * k as i32).abs();
            image::Luma([if d < 4 { 200 } else { 30 + (x % 7) as u8 }])
        });
        let name = format!("images/frame_{k:08}.png");
        img.save(dir.join(&name)).unwrap();
        list.push_str(&format!("{:.6} {name}\n", 0.00025 + 0.04 * k as f64));
    }
    std::fs::write(dir.join("images.txt"), list).unwrap();
    if events_txt {
        std::fs::write(dir.join("events.txt"), "0.000100 3 4 1\n").unwrap();
    }
    dir.join("images.txt")
}

#[test]
fn a_frame_list_is_a_source_like_its_folder() {
    let dir = common::temp_dir("inputs-list");
    let list = export(&dir.join("rec"), false);
    let (by_list, by_folder) = (dir.join("list.csv"), dir.join("folder.csv"));
    ok(&convert(&list, &by_list, &[]));
    ok(&convert(&dir.join("rec"), &by_folder, &[]));
    let got = events(&by_list);
    assert!(got.len() > 100, "{}", got.len());
    assert_eq!(got, events(&by_folder));
    // A times.txt (one time per line, for the images sorted by name) named directly.
    let flat = dir.join("flat");
    std::fs::create_dir_all(&flat).unwrap();
    let mut times = String::new();
    for (k, entry) in std::fs::read_to_string(&list).unwrap().lines().enumerate() {
        let (t, name) = entry.split_once(' ').unwrap();
        std::fs::copy(dir.join("rec").join(name), flat.join(format!("{k:03}.png"))).unwrap();
        times.push_str(t);
        times.push('\n');
    }
    std::fs::write(flat.join("times.txt"), times).unwrap();
    let by_times = dir.join("times.csv");
    ok(&convert(&flat.join("times.txt"), &by_times, &[]));
    assert_eq!(events(&by_times), got);
}

#[test]
fn an_aps_export_is_read_as_linear_and_gray_images_of_unknown_space_are_warned_about() {
    let dir = common::temp_dir("inputs-aps");
    let aps = export(&dir.join("aps"), true);
    let [auto, linear, srgb] = ["auto.csv", "linear.csv", "srgb.csv"].map(|n| dir.join(n));
    let said = ok(&convert(&aps, &auto, &[]));
    assert!(said.contains("recognised as a DAVIS APS export"), "{said}");
    ok(&convert(&aps, &linear, &["--color", "linear"]));
    ok(&convert(&aps, &srgb, &["--color", "srgb"]));
    let (a, l, s) = (events(&auto), events(&linear), events(&srgb));
    assert!(!a.is_empty());
    assert_eq!(a, l, "auto did not read the export as linear");
    assert_ne!(a, s);
    // The old flag still means linear.
    let flag = dir.join("flag.csv");
    ok(&convert(&aps, &flag, &["--linear"]));
    assert_eq!(events(&flag), l);

    // The same images without events.txt: not recognisably an APS export. Read as sRGB, with
    // a warning naming the way out.
    let plain = export(&dir.join("plain"), false);
    let guess = dir.join("guess.csv");
    let said = ok(&convert(plain.parent().unwrap(), &guess, &[]));
    assert!(said.contains("--color linear"), "{said}");
    assert_eq!(events(&guess), s);
}

#[test]
fn a_text_file_is_never_handed_to_ffmpeg() {
    let dir = common::temp_dir("inputs-text");
    for (name, text) in [
        (
            "notes.txt",
            "frames of a walk, shot at 30 fps\nsecond line\n",
        ),
        ("clip.mp4", "this is not a video\n"),
        ("list.txt", "0.0 a.png extra words\n"),
    ] {
        let input = dir.join(name);
        std::fs::write(&input, text).unwrap();
        let out = dir.join(format!("{name}.csv"));
        let run = convert(&input, &out, &[]);
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert!(!run.status.success(), "{name}: accepted");
        assert!(
            stderr.contains("a text file, not a video"),
            "{name}: {stderr}"
        );
        assert!(!out.exists(), "{name}: an output was written");
    }
}
