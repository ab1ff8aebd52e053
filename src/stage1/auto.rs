//! `tier = "auto"`: the learned tier when this machine can hold it at the frame rate budget,
//! the physics tier otherwise.
//!
//! The rule, decided once when Stage 1 is built:
//! 1. the learned tier is opened as configured (`[stage1.learned]`); if it cannot be (no ONNX
//!    Runtime library, a model that does not load or does not fit in memory), physics, with
//!    the reason logged;
//! 2. with a budget (`[stage1] budget_fps`, 30 by default; 0: none, e.g. for `convert`, which
//!    has no deadline), the network is timed on whole frames of this size: a warm-up run and
//!    a measured run of [`PROBE_PAIRS`] pairs (throughput per pair barely changes with the
//!    window: 19.4 and 19.6 pairs/s for 16 and 8 pairs at 346x260, `models/v2ce-small.md`);
//! 3. learned when it runs at least [`HEADROOM`] times the budget in pairs per second, physics
//!    otherwise. Whole frames are the worst case: crops around what moves and skipped still
//!    windows only make the learned tier cheaper, never dearer, so the choice holds whatever
//!    the scene does.
//!
//! The choice and the measured speed are logged and show in the tier's description.

use std::time::Instant;

use crate::error::Result;

use super::{LearnedStage1, PhysicsStage1, SourceEncoding, Stage1, Stage1Config, Tap, Tapped};

/// Frame pairs of the timing runs.
pub const PROBE_PAIRS: usize = 4;

/// The learned tier must run this many times faster than the budget (for the sampler, the
/// sinks, and a busy machine).
pub const HEADROOM: f64 = 1.2;

/// The frame rate budget when `budget_fps` is unset.
pub const DEFAULT_BUDGET_FPS: f64 = 30.0;

/// What `auto` chose, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct Choice {
    /// Whether the learned tier runs.
    pub learned: bool,
    /// Why, in words.
    pub reason: String,
}

/// The rule of the module docs on a measured speed (`None`: the learned tier could not be
/// opened, for `error`).
pub fn decide(pairs_per_s: Option<f64>, budget_fps: f64, error: &str) -> Choice {
    match pairs_per_s {
        None => Choice {
            learned: false,
            reason: format!("the learned tier cannot run here ({error})"),
        },
        Some(_) if budget_fps <= 0.0 => Choice {
            learned: true,
            reason: "no frame rate budget".into(),
        },
        Some(speed) => {
            let need = budget_fps * HEADROOM;
            Choice {
                learned: speed >= need,
                reason: format!(
                    "the network runs {speed:.1} pairs/s on whole frames, {} the {need:.1} a \
                     budget of {budget_fps} fps needs ({HEADROOM}x)",
                    if speed >= need {
                        "at least"
                    } else {
                        "less than"
                    }
                ),
            }
        }
    }
}

/// Builds the tier `auto` chooses for frames of `size` (see the module docs).
pub fn build(
    config: &Stage1Config,
    bins: usize,
    size: (u16, u16),
    encoding: SourceEncoding,
) -> Result<Box<dyn Stage1>> {
    let budget = config.budget_fps;
    let (learned, speed, error) = match LearnedStage1::new(&config.learned, bins, size, encoding) {
        Ok(mut l) => {
            let speed = if budget > 0.0 {
                l.probe(PROBE_PAIRS)?;
                let started = Instant::now();
                l.probe(PROBE_PAIRS)?;
                PROBE_PAIRS as f64 / started.elapsed().as_secs_f64().max(1e-9)
            } else {
                f64::INFINITY
            };
            (Some(l), Some(speed), String::new())
        }
        Err(e) => (None, None, e.to_string()),
    };
    let choice = decide(speed, budget, &error);
    tracing::info!(
        "Stage 1 auto: {} ({})",
        if choice.learned { "learned" } else { "physics" },
        choice.reason
    );
    let inner: Box<dyn Stage1> = match learned {
        Some(l) if choice.learned => Box::new(l),
        _ => Box::new(PhysicsStage1::new(config, bins, size)?),
    };
    Ok(Box::new(Tapped::new(inner, choice)))
}

/// The reason `auto` chose the tier, added to its description.
impl Tap for Choice {
    fn describe(&self, tier: String) -> String {
        format!("{tier}, chosen by auto: {}", self.reason)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rule() {
        assert!(!decide(None, 30.0, "no library").learned);
        assert!(decide(None, 0.0, "x").reason.contains("cannot run"));
        assert!(decide(Some(1.0), 0.0, "").learned);
        assert!(decide(Some(36.0), 30.0, "").learned);
        let slow = decide(Some(35.9), 30.0, "");
        assert!(!slow.learned);
        assert!(slow.reason.contains("35.9 pairs/s"), "{}", slow.reason);
    }
}
