//! Dataset-scale conversion as a well-behaved task of a cluster engine (`v2ce batch`): a manifest
//! of inputs, a deterministic share of it per task (Slurm job arrays, Kubernetes Indexed Jobs),
//! each output written under a temporary name and renamed when complete, and a per-shard JSONL
//! ledger that lets a killed or pre-empted task resume with nothing lost or converted twice.
//!
//! - [`Manifest`]: the inputs, from a list (`path [key=value ...]` per line), JSON lines
//!   (`{"input": ..., "fps": ...}`) or a glob, with per-item settings (`manifest.rs`).
//! - [`Options`]: how a task converts, from the command line's [`Flags`] and the environment:
//!   which shard it takes (`--shard I/N`, a Slurm job array, a Kubernetes Indexed Job) and how
//!   many threads (`options.rs`). Items are spread over the shards by size (largest first, each
//!   to the least-loaded shard), not by position (`shard.rs`).
//! - [`run`]: converts the shard's items ([`crate::convert::convert_file`], as `v2ce convert`
//!   does), skipping what its ledger records as done with the same input and settings
//!   (`run.rs`, one item in `item.rs`, the hashes of inputs and settings in `hash.rs`, the
//!   ledger in `ledger.rs`); what it did in a [`run::ShardSummary`].
//! - [`report`]: every shard's ledger merged into one [`report::Report`] (`report.rs`).
//! - Outputs normalised and checked (none into the ledgers' folder, no two one file) in
//!   `paths.rs`; the manifest, ledgers and config read with bounds on line and file size in
//!   `lines.rs`.

mod hash;
mod item;
mod ledger;
mod lines;
mod manifest;
mod options;
mod paths;
mod report;
mod run;
mod shard;

pub use manifest::Manifest;
pub use options::{Flags, Options};
pub use report::report;
pub use run::run;
