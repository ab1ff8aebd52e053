//! Tests on the real recordings in `../shared/data` (not part of the repository). Each test prints
//! why it skips when the data is absent; set `V2CE_DATA` to point elsewhere.

mod common;

use v2ce::format::{self, Recording};
use v2ce::interval::{fixed_intervals, intervals_from_frames, Interval};
use v2ce::stage2::SamplerKind;

/// Time of the first frame's exposure start in the IJRR export (its README).
const IJRR_T0: i64 = 1_589_163_147_364_965;

#[test]
fn aedat4_and_ijrr_readers_agree_on_davis346() {
    let d = data_or_skip!("aedat4_and_ijrr_readers_agree_on_davis346");
    let aedat = format::read_events(&d.join("davis346/davis346.aedat4")).unwrap();
    let ijrr = format::read_events(&d.join("davis346/ijrr_export/events.txt")).unwrap();
    assert_eq!((aedat.width, aedat.height), (346, 260));
    assert_eq!(aedat.events.len(), 78_830);
    let on = aedat.events.events().iter().filter(|e| e.on).count();
    assert_eq!(on, 41_257);
    // Same events; the export's times are relative to IJRR_T0.
    assert_eq!(ijrr.events.len(), aedat.events.len());
    for (a, b) in aedat.events.events().iter().zip(ijrr.events.events()) {
        assert_eq!((a.t - IJRR_T0, a.x, a.y, a.on), (b.t, b.x, b.y, b.on));
    }
    let frames = format::read_frame_times(&d.join("davis346/davis346.aedat4")).unwrap();
    let images = format::read_frame_times(&d.join("davis346/ijrr_export/images.txt")).unwrap();
    assert_eq!(frames.len(), 59);
    let rel: Vec<i64> = frames.iter().map(|t| t - IJRR_T0).collect();
    assert_eq!(rel, images);
}

fn score(rec: &Recording, intervals: &[Interval], kind: SamplerKind) -> v2ce::eval::Stage2Report {
    let sampler = kind.build(42);
    v2ce::eval::stage2(rec, intervals, 10, sampler.as_ref(), |_| Ok(())).unwrap()
}

/// The floor set by the reference implementation on the same frame-normalised voxels
/// (issue 2): LDATI C-METE 94.0 us on davis346 and 79.5 us on dvxplorer; ours must keep every
/// event (PGER exactly 1) and do no worse, and the default sampler must beat LDATI; the
/// `spatial` sampler must reach issue 28's bound (40 us on davis346, 32 us on dvxplorer) and
/// beat `moment`.
#[test]
fn stage2_on_davis346_with_aps_frame_intervals() {
    let d = data_or_skip!("stage2_on_davis346_with_aps_frame_intervals");
    let path = d.join("davis346/davis346.aedat4");
    let rec = format::read_events(&path).unwrap();
    let intervals = intervals_from_frames(&format::read_frame_times(&path).unwrap()).unwrap();
    check_floor(&rec, &intervals, 94.0, 40.0);
}

#[test]
fn stage2_on_dvxplorer_at_30_fps() {
    let d = data_or_skip!("stage2_on_dvxplorer_at_30_fps");
    let rec = format::read_events(&d.join("dvxplorer/data_sample.aedat4")).unwrap();
    let ev = rec.events.events();
    let intervals = fixed_intervals(ev[0].t, ev[ev.len() - 1].t, 30.0).unwrap();
    check_floor(&rec, &intervals, 79.5, 32.0);
}

fn check_floor(rec: &Recording, intervals: &[Interval], ldati_floor_us: f64, spatial_us: f64) {
    let ldati = score(rec, intervals, SamplerKind::Ldati);
    let m = ldati.metrics;
    eprintln!("ldati: {m:?}");
    assert_eq!(m.events_out, m.events_in);
    assert_eq!(m.pger, 1.0);
    assert_eq!(m.noe, 0.0);
    assert!(
        m.c_mete_us <= ldati_floor_us,
        "ldati C-METE {}",
        m.c_mete_us
    );
    let default = score(rec, intervals, SamplerKind::DEFAULT).metrics;
    eprintln!("default: {default:?}");
    assert_eq!(default.pger, 1.0);
    assert!(default.c_mete_us < m.c_mete_us);
    let moment = score(rec, intervals, SamplerKind::Moment).metrics;
    let spatial = score(rec, intervals, SamplerKind::Spatial).metrics;
    eprintln!("moment: {moment:?}\nspatial: {spatial:?}");
    assert_eq!((spatial.pger, spatial.events_out), (1.0, spatial.events_in));
    assert!(
        spatial.c_mete_us <= spatial_us && spatial.c_mete_us < moment.c_mete_us,
        "spatial {} us, moment {} us",
        spatial.c_mete_us,
        moment.c_mete_us
    );
    // The baselines are an order of magnitude worse (the paper's finding).
    for kind in [SamplerKind::Even, SamplerKind::Random] {
        let b = score(rec, intervals, kind).metrics;
        assert!(b.c_mete_us > 10.0 * m.c_mete_us, "{kind}: {b:?}");
        assert!((b.pger - 1.0).abs() < 0.01, "{kind}: {b:?}");
    }
}

/// Every recording, with the event count faery reports for it (the data README).
const RECORDINGS: [(&str, usize); 5] = [
    ("davis346/davis346.aedat4", 78_830),
    ("dvxplorer/data_sample.aedat4", 323_963),
    ("prophesee/sparklers.raw", 521_252),
    ("prophesee/evt2_sample.raw", 539_481),
    ("prophesee/evt3_sample.raw", 219_596),
];

/// Each recording decodes to faery's count, in time order and inside its sensor, and comes
/// back identical (t, x, y, on, and order) after encoding to every format and decoding again.
#[test]
fn every_recording_round_trips_through_every_format() {
    use v2ce::format::{Compression, Format};
    let d = data_or_skip!("every_recording_round_trips_through_every_format");
    let out = std::env::temp_dir().join(format!("v2ce-rt-{}", std::process::id()));
    std::fs::create_dir_all(&out).unwrap();
    for (name, count) in RECORDINGS {
        let rec = format::read_events(&d.join(name)).unwrap();
        let events = rec.events.events();
        assert_eq!(events.len(), count, "{name}");
        assert!(
            events.iter().all(|e| e.x < rec.width && e.y < rec.height),
            "{name}"
        );
        for (file, format) in [
            ("a.aedat4", Format::Aedat4(Compression::Lz4)),
            ("b.aedat4", Format::Aedat4(Compression::Zstd)),
            ("c.aedat4", Format::Aedat4(Compression::None)),
            ("e2.raw", Format::Evt2),
            ("e3.raw", Format::Evt3),
            ("e.csv", Format::Csv),
            ("e.npz", Format::Npz),
            ("e.h5", Format::Hdf5),
        ] {
            let path = out.join(file);
            let mut enc = format::create(&path, format, rec.width, rec.height).unwrap();
            for chunk in events.chunks(10_007) {
                enc.write(chunk).unwrap();
            }
            enc.finish().unwrap();
            let back = format::read_events(&path).unwrap();
            assert!(back.events.events() == events, "{name} through {file}");
            // CSV and the toolbox's .npz carry no sensor size.
            if !matches!(format, Format::Csv | Format::Npz) {
                assert_eq!((back.width, back.height), (rec.width, rec.height), "{name}");
            }
        }
    }
    std::fs::remove_dir_all(&out).unwrap();
}

/// The APS frames read from the AEDAT 4.0 file and from the IJRR PNG export (as linear values)
/// are the same images, 40 ms apart.
#[test]
fn aps_frames_match_the_png_export() {
    use v2ce::frame;
    let d = data_or_skip!("aps_frames_match_the_png_export");
    let mut aps = frame::open(&d.join("davis346/davis346.aedat4"), &Default::default()).unwrap();
    let options = frame::SourceOptions {
        fps: None,
        color: frame::images::ColorSpace::Linear,
        topic: None,
    };
    let mut png = frame::open(&d.join("davis346/ijrr_export"), &options).unwrap();
    assert_eq!(aps.size(), (346, 260));
    let mut n = 0;
    while let Some(a) = aps.next_frame().unwrap() {
        let b = png.next_frame().unwrap().unwrap();
        assert_eq!(a.luma, b.luma, "frame {n}");
        assert_eq!(a.t - IJRR_T0, b.t, "frame {n}");
        n += 1;
    }
    assert!(png.next_frame().unwrap().is_none());
    assert_eq!(n, 59);
}

/// `v2ce convert` on the AEDAT 4.0 file and on its PNG export (its `images.txt` given as the
/// input, colour space left to `auto`, which recognises the export) gives the same events,
/// every time to the microsecond once the export's origin is added back.
#[test]
fn converting_the_aedat4_and_its_png_export_gives_the_same_events() {
    let d = data_or_skip!("converting_the_aedat4_and_its_png_export_gives_the_same_events");
    let out = std::env::temp_dir().join(format!("v2ce-aps-vs-png-{}", std::process::id()));
    std::fs::create_dir_all(&out).unwrap();
    let convert = |input: &std::path::Path, name: &str| {
        let path = out.join(name);
        let run = std::process::Command::new(env!("CARGO_BIN_EXE_v2ce"))
            .arg("convert")
            .arg(input)
            .arg("-o")
            .arg(&path)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&run.stderr).to_string();
        assert!(run.status.success(), "{stderr}");
        (format::read_events(&path).unwrap(), stderr)
    };
    let (aedat, _) = convert(&d.join("davis346/davis346.aedat4"), "aedat4.csv");
    let (png, said) = convert(&d.join("davis346/ijrr_export/images.txt"), "png.csv");
    assert!(said.contains("recognised as a DAVIS APS export"), "{said}");
    let shifted: Vec<_> = png
        .events
        .events()
        .iter()
        .map(|e| v2ce::event::Event::new(e.t + IJRR_T0, e.x, e.y, e.on))
        .collect();
    assert!(aedat.events.len() > 10_000, "{}", aedat.events.len());
    let differ = aedat
        .events
        .events()
        .iter()
        .zip(&shifted)
        .filter(|(a, b)| a != b)
        .count();
    assert_eq!(aedat.events.len(), shifted.len());
    assert_eq!(differ, 0, "{differ} of {} events differ", shifted.len());
    std::fs::remove_dir_all(&out).unwrap();
}

/// `v2ce calibrate` on the davis346 clip: fitted on each half of its intervals, it scores on
/// the other half at least as well as the shipped preset (TF1 within 0.03), and the preset file
/// it writes, given to `convert --preset-file`, reproduces the real event count.
#[test]
fn calibrate_fits_davis346_and_its_preset_file_converts() {
    let d = data_or_skip!("calibrate_fits_davis346_and_its_preset_file_converts");
    let rec = d.join("davis346/davis346.aedat4");
    let out = std::env::temp_dir().join(format!("v2ce-calibrate-{}", std::process::id()));
    std::fs::create_dir_all(&out).unwrap();
    let preset = out.join("sensor.toml");
    let run = |args: &[&std::ffi::OsStr]| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_v2ce"))
            .args(args)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        o
    };
    let o = run(&[
        "calibrate".as_ref(),
        "--real".as_ref(),
        rec.as_os_str(),
        "-o".as_ref(),
        preset.as_os_str(),
        "--json".as_ref(),
    ]);
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    eprintln!("calibrate: {report}");
    for h in report["held_out"].as_array().unwrap() {
        let (fitted, base) = (
            h["fitted"]["tf1"].as_f64().unwrap(),
            h["base"]["tf1"].as_f64().unwrap(),
        );
        assert!(fitted >= base - 0.03, "{h}");
        assert!(fitted > h["ideal"]["tf1"].as_f64().unwrap(), "{h}");
    }
    let sim = out.join("sim.csv");
    run(&[
        "convert".as_ref(),
        rec.as_os_str(),
        "--preset-file".as_ref(),
        preset.as_os_str(),
        "-o".as_ref(),
        sim.as_os_str(),
    ]);
    let o = run(&[
        "eval".as_ref(),
        "stage1".as_ref(),
        "--real".as_ref(),
        rec.as_os_str(),
        "--sim".as_ref(),
        sim.as_os_str(),
        "--json".as_ref(),
    ]);
    let scores: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let ratio = scores["count_ratio"].as_f64().unwrap();
    eprintln!(
        "convert --preset-file: TF1 {} count ratio {ratio}",
        scores["tf1"]
    );
    assert!((0.9..=1.1).contains(&ratio), "{scores}");
    // `eval stage1` simulates by itself when given no --sim: the same scores.
    let o = run(&[
        "eval".as_ref(),
        "stage1".as_ref(),
        "--real".as_ref(),
        rec.as_os_str(),
        "--preset-file".as_ref(),
        preset.as_os_str(),
        "--json".as_ref(),
    ]);
    let direct: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(direct, scores);
    std::fs::remove_dir_all(&out).unwrap();
}

/// The physics tier on the davis346 APS frames, scored against the real events: the default
/// DAVIS346 preset beats the noiseless ideal sensor on TF1 and TPF1 with an event count within
/// 0.5 to 2 times the real one.
#[test]
fn physics_tier_on_davis346_beats_the_noiseless_sensor() {
    use v2ce::config::Config;
    use v2ce::stage1::Preset;
    let d = data_or_skip!("physics_tier_on_davis346_beats_the_noiseless_sensor");
    let path = d.join("davis346/davis346.aedat4");
    let (real, frames) = format::aedat4::read(&path).unwrap();
    let intervals = intervals_from_frames(&frames).unwrap();
    let score = |preset: Preset| {
        let mut config = Config::default();
        config.stage1.preset = preset;
        let source = v2ce::frame::open(&path, &Default::default()).unwrap();
        let out = std::env::temp_dir().join(format!(
            "v2ce-p-{}-{}.csv",
            preset.name(),
            std::process::id()
        ));
        let sink = v2ce::sink::file::FileSink::create(&out, format::Format::Csv, 346, 260).unwrap();
        let sinks: Vec<Box<dyn v2ce::sink::Sink>> = vec![Box::new(sink)];
        let stop = std::sync::atomic::AtomicBool::new(false);
        let stage1 = v2ce::convert::build_stage1(&config, source.as_ref()).unwrap();
        v2ce::convert::convert(source, stage1, &config, sinks, None, &stop, |_| {}).unwrap();
        let sim = format::read_events(&out).unwrap();
        std::fs::remove_file(&out).unwrap();
        v2ce::metrics::stage1::score(
            real.events.events(),
            sim.events.events(),
            &intervals,
            346,
            260,
            10,
        )
        .unwrap()
    };
    let default = score(Preset::Davis346);
    let ideal = score(Preset::Ideal);
    eprintln!("davis346 preset: {default:?}\nideal: {ideal:?}");
    assert!(default.tf1 > ideal.tf1 && default.tpf1 > ideal.tpf1);
    assert!(
        (0.5..=2.0).contains(&default.count_ratio()),
        "{}",
        default.count_ratio()
    );
    assert!(default.tf1 >= 0.40, "{}", default.tf1);
}

/// The default physics tier sees the motion between the davis346 clip's frames (sub-frames
/// along the optical flow): TF1 at least 0.66 at a count within 0.8-1.25 of the real one
/// (measured: 0.707 at 1.024), where interpolating each pixel linearly gives at least 0.03 less
/// (measured: 0.647).
#[test]
fn the_default_physics_tier_sees_motion_on_davis346() {
    let d = data_or_skip!("the_default_physics_tier_sees_motion_on_davis346");
    let rec = d.join("davis346/davis346.aedat4");
    let out = std::env::temp_dir().join(format!("v2ce-motion-{}", std::process::id()));
    std::fs::create_dir_all(&out).unwrap();
    // `extra`: flags after the defaults.
    let score = |name: &str, extra: &[&str]| {
        let sim = out.join(format!("{name}.csv"));
        let mut convert: Vec<std::ffi::OsString> = vec![
            "convert".into(),
            rec.clone().into_os_string(),
            "-o".into(),
            sim.clone().into_os_string(),
        ];
        convert.extend(extra.iter().map(|a| a.into()));
        for args in [
            convert,
            vec![
                "eval".into(),
                "stage1".into(),
                "--real".into(),
                rec.clone().into_os_string(),
                "--sim".into(),
                sim.clone().into_os_string(),
                "--json".into(),
            ],
        ] {
            let o = std::process::Command::new(env!("CARGO_BIN_EXE_v2ce"))
                .args(&args)
                .output()
                .unwrap();
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
            if args[0] == "eval" {
                let s: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
                return (
                    s["tf1"].as_f64().unwrap(),
                    s["count_ratio"].as_f64().unwrap(),
                );
            }
        }
        unreachable!()
    };
    let (flow, ratio) = score("default", &[]);
    let (linear, _) = score("linear", &["--motion", "linear"]);
    eprintln!("davis346: TF1 {flow:.3} (count ratio {ratio:.3}) with flow, {linear:.3} linear");
    assert!(
        flow >= 0.66 && (0.8..=1.25).contains(&ratio),
        "{flow} {ratio}"
    );
    assert!(linear < flow - 0.03, "{linear} against {flow}");
    std::fs::remove_dir_all(&out).unwrap();
}

/// `v2ce eval realism` on the davis346 clip and its APS frames: every statistic of the issue,
/// each a finite number or null; the recording against itself is at distance 0 on every
/// statistic it defines; the noise floor (which needs frames) is defined there and undefined
/// on the dvxplorer recording measured at a fixed rate.
#[test]
fn realism_statistics_on_the_shared_recordings() {
    let d = data_or_skip!("realism_statistics_on_the_shared_recordings");
    let run = |args: &[&std::ffi::OsStr]| -> serde_json::Value {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_v2ce"))
            .args(["eval", "realism", "--json"])
            .args(args)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{args:?}: {err}");
        serde_json::from_slice(&out.stdout).unwrap()
    };
    let davis = d.join("davis346/davis346.aedat4");
    let stat = |json: &serde_json::Value, name: &str| -> serde_json::Value {
        json["statistics"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["name"] == name)
            .unwrap_or_else(|| panic!("{name} missing in {json}"))
            .clone()
    };
    let names = [
        "rate_per_pixel",
        "firing_pixels",
        "inter_event_interval",
        "refractory_floor",
        "timestamp_batching",
        "neighbour_batching",
        "on_share",
        "on_off_alternation",
        "noise_floor_dark",
        "noise_floor_bright",
        "noise_floor_on_share",
        "rate_spectrum_peak",
    ];
    let simulated = run(&["--real".as_ref(), davis.as_os_str()]);
    assert!(
        simulated["sim_events"].as_u64().unwrap() > 10_000,
        "{simulated}"
    );
    for name in names {
        let s = stat(&simulated, name);
        for key in ["real", "sim", "distance"] {
            assert!(s[key].is_number(), "{name}.{key} in {simulated}");
        }
    }
    let itself = run(&[
        "--real".as_ref(),
        davis.as_os_str(),
        "--sim".as_ref(),
        davis.as_os_str(),
    ]);
    for name in names {
        let s = stat(&itself, name);
        assert_eq!(s["real"], s["sim"], "{name}");
        assert_eq!(s["distance"], 0.0, "{name}");
    }
    let dvx = d.join("dvxplorer/data_sample.aedat4");
    let fixed = run(&[
        "--real".as_ref(),
        dvx.as_os_str(),
        "--sim".as_ref(),
        dvx.as_os_str(),
        "--fps".as_ref(),
        "30".as_ref(),
    ]);
    assert!(
        stat(&fixed, "noise_floor_dark")["real"].is_null(),
        "{fixed}"
    );
    assert_eq!(stat(&fixed, "inter_event_interval")["distance"], 0.0);
    // No frames: simulated from frames reconstructed from its events; every statistic that
    // needs no frames is defined.
    let rebuilt = run(&[
        "--real".as_ref(),
        dvx.as_os_str(),
        "--fps".as_ref(),
        "30".as_ref(),
        "--preset".as_ref(),
        "dvxplorer".as_ref(),
    ]);
    assert!(
        rebuilt["sim_events"].as_u64().unwrap() > 50_000,
        "{rebuilt}"
    );
    for name in names.iter().filter(|n| !n.starts_with("noise_floor")) {
        let s = stat(&rebuilt, name);
        for key in ["real", "sim", "distance"] {
            assert!(s[key].is_number(), "{name}.{key} in {rebuilt}");
        }
    }
}

/// The default preset's noise is closer to the davis346 clip than the same sensor without
/// noise (the "a score that silence does not win") on the noise floor and the
/// inter-event intervals: the distances of the dark and bright floors, of their ON share and
/// of the same-polarity intervals, summed over five seeds (mismatch and noise move the small
/// floor counts from seed to seed). Measured, per seed: 0.089 against 0.251 decades for the
/// two floors, 0.19 against 0.28 for the ON share, 0.103 against 0.117 for the intervals.
#[test]
fn the_default_noise_is_closer_to_the_noise_floor_and_intervals_than_silence() {
    let d =
        data_or_skip!("the_default_noise_is_closer_to_the_noise_floor_and_intervals_than_silence");
    let davis = d.join("davis346/davis346.aedat4");
    let dir = std::env::temp_dir().join(format!("v2ce-floor-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let quiet = dir.join("noise-off.toml");
    std::fs::write(
        &quiet,
        "[stage1.physics]\nleak_hz = 0.0\nshot_noise_hz = 0.0\nhot_pixel_fraction = 0.0\n\
         threshold_noise = 0.0\n",
    )
    .unwrap();
    let v2ce = |args: &[&std::ffi::OsStr]| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_v2ce"))
            .args(args)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        o.stdout
    };
    // Per variant: the summed floor distances, the ON share's and the intervals'.
    let mut sums = [[0.0f64; 3]; 2];
    for seed in 0..5u32 {
        for (k, config) in [None, Some(&quiet)].into_iter().enumerate() {
            let sim = dir.join(format!("s{seed}-{k}.csv"));
            let seed = seed.to_string();
            let mut args: Vec<&std::ffi::OsStr> = vec![
                "convert".as_ref(),
                davis.as_os_str(),
                "-o".as_ref(),
                sim.as_os_str(),
                "--seed".as_ref(),
                seed.as_ref(),
            ];
            if let Some(c) = config {
                args.extend(["--config".as_ref(), c.as_os_str()]);
            }
            v2ce(&args);
            let out = v2ce(&[
                "eval".as_ref(),
                "realism".as_ref(),
                "--json".as_ref(),
                "--real".as_ref(),
                davis.as_os_str(),
                "--sim".as_ref(),
                sim.as_os_str(),
            ]);
            let json: serde_json::Value = serde_json::from_slice(&out).unwrap();
            let distance = |name: &str| {
                json["statistics"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .find(|s| s["name"] == name)
                    .and_then(|s| s["distance"].as_f64())
                    .unwrap_or_else(|| panic!("{name} undefined in {json}"))
            };
            sums[k][0] += distance("noise_floor_dark") + distance("noise_floor_bright");
            sums[k][1] += distance("noise_floor_on_share");
            sums[k][2] += distance("inter_event_interval");
        }
    }
    eprintln!(
        "floors, ON share and intervals, default {:?}, noise off {:?}",
        sums[0], sums[1]
    );
    for (statistic, (default, quiet)) in ["floors", "ON share", "intervals"]
        .iter()
        .zip(sums[0].iter().zip(&sums[1]))
    {
        assert!(default < quiet, "{statistic}: {sums:?}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
