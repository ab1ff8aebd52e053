//! Writes the raw V4L2 bindings for one target from `wrapper.h`: `generate TARGET SYSROOT OUT
//! [INCLUDE_DIR]` (see ../generate.sh; headers in `INCLUDE_DIR` come before the sysroot's). The options are bindgen's defaults, as the upstream crate's build
//! script uses, so the bindings are the ones a build with libclang would generate.

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let (target, sysroot, out, include) = match &args[..] {
        [_, t, s, o] => (t, s, o, None),
        [_, t, s, o, i] => (t, s, o, Some(i)),
        _ => {
            eprintln!("usage: generate TARGET SYSROOT OUT [INCLUDE_DIR]");
            std::process::exit(2);
        }
    };
    let mut builder = bindgen::Builder::default()
        .header("wrapper.h")
        .clang_arg(format!("--target={target}"))
        .clang_arg(format!("--sysroot={sysroot}"));
    if let Some(dir) = include {
        builder = builder.clang_arg(format!("-isystem{dir}"));
    }
    let bindings = builder
        .generate()
        .unwrap_or_else(|e| {
            eprintln!("bindgen failed: {e}");
            std::process::exit(1);
        });
    if let Err(e) = bindings.write_to_file(out) {
        eprintln!("{out}: {e}");
        std::process::exit(1);
    }
}
