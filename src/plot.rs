//! What every plot the program draws (plotters, to PNG) shares: the font for its text.

use crate::error::Result;

/// Where the plots' font is looked for (Debian's `fonts-dejavu-core`, and other common places);
/// `V2CE_FONT` names another TrueType file.
const FONTS: &[&str] = &[
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/liberation-sans/LiberationSans-Regular.ttf",
];

/// Registers a TrueType font for the plots' text, once per process.
pub(crate) fn register_font() -> Result<()> {
    use std::sync::OnceLock;
    static DONE: OnceLock<std::result::Result<(), String>> = OnceLock::new();
    DONE.get_or_init(|| {
        let env = std::env::var_os("V2CE_FONT").map(std::path::PathBuf::from);
        let candidates = env
            .into_iter()
            .chain(FONTS.iter().map(std::path::PathBuf::from));
        for path in candidates {
            if let Ok(bytes) = std::fs::read(&path) {
                // The plotting crate keeps fonts for the process's life.
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font(
                    "sans-serif",
                    plotters::style::FontStyle::Normal,
                    bytes,
                )
                .is_ok()
                {
                    return Ok(());
                }
            }
        }
        Err(format!(
            "no font for the plot's text: install fonts-dejavu-core (apt) or set V2CE_FONT to a \
             .ttf file (looked in {})",
            FONTS.join(", ")
        ))
    })
    .clone()
    .map_err(|e| crate::Error::invalid("plot", e))
}
