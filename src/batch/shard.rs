//! Which share of a manifest this task takes: from `--shard I/N`, a Slurm job array or a
//! Kubernetes Indexed Job; items are spread by size, not by position.

use std::ffi::OsString;

use super::manifest::Item;
use crate::error::{Error, Result};

/// This task's share: shard `index` of `count` (from 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Shard {
    /// From 0.
    pub index: u32,
    /// At least 1.
    pub count: u32,
}

impl Shard {
    /// Everything, as one shard.
    pub const ALL: Shard = Shard { index: 0, count: 1 };

    /// Parses `I/N` (I from 0 to N-1).
    pub fn parse(text: &str) -> Result<Shard> {
        let bad = || {
            Error::invalid(
                "--shard",
                format!("'{text}' (expected I/N with 0 <= I < N, e.g. 0/4)"),
            )
        };
        let (i, n) = text.split_once('/').ok_or_else(bad)?;
        let index: u32 = i.trim().parse().map_err(|_| bad())?;
        let count: u32 = n.trim().parse().map_err(|_| bad())?;
        Shard::new(index, count).map_err(|_| bad())
    }

    /// Shard `index` of `count`.
    pub fn new(index: u32, count: u32) -> Result<Shard> {
        if count == 0 || index >= count {
            return Err(Error::invalid(
                "shard",
                format!("{index} of {count}: the index must be below the count"),
            ));
        }
        Ok(Shard { index, count })
    }

    /// The shard the environment gives: a Slurm job array's task (`SLURM_ARRAY_TASK_ID`,
    /// `SLURM_ARRAY_TASK_COUNT`, less `SLURM_ARRAY_TASK_MIN`, over `SLURM_ARRAY_TASK_STEP`), or
    /// a Kubernetes Indexed Job's `JOB_COMPLETION_INDEX` with `count` (`--shards`, or
    /// `V2CE_SHARDS`); `None` when neither is set. `var` reads a variable as the OS holds it
    /// (`std::env::var_os`): a value that is not UTF-8 is refused, naming the variable, not
    /// taken as unset (which would make the task convert the whole manifest).
    pub fn from_env(
        var: impl Fn(&str) -> Option<OsString>,
        count: Option<u32>,
    ) -> Result<Option<Shard>> {
        let num = |name: &str| -> Result<Option<u64>> {
            let Some(raw) = var(name) else {
                return Ok(None);
            };
            let v = raw.to_str().ok_or_else(|| {
                Error::invalid(
                    "shard",
                    format!("{name}={raw:?} is not UTF-8 (expected a whole number)"),
                )
            })?;
            v.trim()
                .parse::<u64>()
                .map(Some)
                .map_err(|_| Error::invalid("shard", format!("{name}={v} is not a whole number")))
        };
        if let Some(id) = num("SLURM_ARRAY_TASK_ID")? {
            let total = num("SLURM_ARRAY_TASK_COUNT")?.ok_or_else(|| {
                Error::invalid(
                    "shard",
                    "SLURM_ARRAY_TASK_ID without SLURM_ARRAY_TASK_COUNT",
                )
            })?;
            let min = num("SLURM_ARRAY_TASK_MIN")?.unwrap_or(0);
            let step = num("SLURM_ARRAY_TASK_STEP")?.unwrap_or(1).max(1);
            let index = id.saturating_sub(min) / step;
            return Shard::new(
                narrow("a Slurm task index", index)?,
                narrow("SLURM_ARRAY_TASK_COUNT", total)?,
            )
            .map(Some);
        }
        if let Some(index) = num("JOB_COMPLETION_INDEX")? {
            let count = match count {
                Some(c) => u64::from(c),
                None => num("V2CE_SHARDS")?.ok_or_else(|| {
                    Error::invalid(
                        "shard",
                        "JOB_COMPLETION_INDEX is set: give the Job's completions as --shards N or V2CE_SHARDS",
                    )
                })?,
            };
            return Shard::new(
                narrow("JOB_COMPLETION_INDEX", index)?,
                narrow("the shard count", count)?,
            )
            .map(Some);
        }
        Ok(None)
    }

    /// The items of this shard, in manifest order: items sorted by size (largest first, then
    /// by name) each go to the least-loaded shard (the lowest index on a tie). Every task
    /// computes the same split from the same manifest. Only the first `min(count, items)`
    /// shards can receive an item (an empty shard always wins a tie by its lower index), so
    /// the work and memory follow the manifest, not the shard count (`--shard 0/4000000000`).
    pub fn select<'a>(&self, items: &'a [Item]) -> Vec<&'a Item> {
        use std::cmp::Reverse;
        let mut order: Vec<usize> = (0..items.len()).collect();
        order.sort_by(|&a, &b| {
            items[b]
                .bytes
                .cmp(&items[a].bytes)
                .then_with(|| items[a].name.cmp(&items[b].name))
        });
        let used = (self.count as usize).min(items.len());
        // (load, shard), least first.
        let mut load: std::collections::BinaryHeap<Reverse<(u64, usize)>> =
            (0..used).map(|s| Reverse((0, s))).collect();
        let mut mine = vec![false; items.len()];
        for i in order {
            let Some(Reverse((l, shard))) = load.pop() else {
                break;
            };
            // Count an empty file as one byte, so empty inputs spread too.
            load.push(Reverse((l.saturating_add(items[i].bytes.max(1)), shard)));
            mine[i] = shard == self.index as usize;
        }
        items
            .iter()
            .zip(mine)
            .filter_map(|(it, m)| m.then_some(it))
            .collect()
    }
}

/// A shard number from the environment, refused rather than clamped past `u32::MAX` (a clamped
/// count would split the manifest differently from the other tasks).
fn narrow(what: &str, v: u64) -> Result<u32> {
    u32::try_from(v)
        .map_err(|_| Error::invalid("shard", format!("{what} {v} is above {} shards", u32::MAX)))
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::batch::manifest::{default_output, Settings};

    fn item(name: &str, bytes: u64) -> Item {
        Item {
            name: name.into(),
            input: name.into(),
            output: default_output(name, "aedat4").unwrap(),
            settings: Settings::default(),
            bytes,
        }
    }

    #[test]
    fn shards_cover_every_item_once_balanced_by_size() {
        let items: Vec<Item> = (0..23)
            .map(|i| item(&format!("c{i}.mp4"), 1000 + (i * 7919 % 50_000)))
            .collect();
        for count in [1u32, 2, 4, 7, 30] {
            let mut seen = vec![0; items.len()];
            let mut loads = Vec::new();
            for index in 0..count {
                let shard = Shard::new(index, count).unwrap();
                let mine = shard.select(&items);
                // The same split every time.
                assert_eq!(mine, shard.select(&items));
                loads.push(mine.iter().map(|i| i.bytes).sum::<u64>());
                for m in mine {
                    seen[items.iter().position(|i| i.name == m.name).unwrap()] += 1;
                }
            }
            assert!(seen.iter().all(|&n| n == 1), "{count}: {seen:?}");
            let biggest = items.iter().map(|i| i.bytes).max().unwrap();
            let (lo, hi) = (loads.iter().min().unwrap(), loads.iter().max().unwrap());
            if count as usize <= items.len() {
                // Greedy largest-first: no shard exceeds another by more than one item.
                assert!(hi - lo <= biggest, "{count}: {loads:?}");
            }
        }
        // By size, not position: the two largest go to different shards.
        let items = vec![item("a", 100), item("b", 100), item("c", 1), item("d", 1)];
        let first = Shard::new(0, 2).unwrap().select(&items);
        assert_eq!(
            first.iter().map(|i| i.name.as_str()).collect::<Vec<_>>(),
            ["a", "c"]
        );
    }

    /// The split as first written: a load per shard, the least loaded found by a scan.
    fn select_by_scan(shard: Shard, items: &[Item]) -> Vec<&Item> {
        let mut order: Vec<usize> = (0..items.len()).collect();
        order.sort_by(|&a, &b| {
            items[b]
                .bytes
                .cmp(&items[a].bytes)
                .then_with(|| items[a].name.cmp(&items[b].name))
        });
        let mut load = vec![0u64; shard.count as usize];
        let mut mine = vec![false; items.len()];
        for i in order {
            let (s, _) = load
                .iter()
                .enumerate()
                .min_by_key(|&(s, l)| (*l, s))
                .unwrap();
            load[s] += items[i].bytes.max(1);
            mine[i] = s == shard.index as usize;
        }
        items
            .iter()
            .zip(mine)
            .filter_map(|(it, m)| m.then_some(it))
            .collect()
    }

    #[test]
    fn a_huge_shard_count_costs_what_the_manifest_does_and_splits_the_same() {
        let items: Vec<Item> = (0..40)
            .map(|i| item(&format!("v{i}.mp4"), (i * 7919 % 13) as u64 * 1000))
            .collect();
        for count in [1u32, 3, 8, 39, 40, 41, 100] {
            for index in 0..count {
                let shard = Shard::new(index, count).unwrap();
                assert_eq!(shard.select(&items), select_by_scan(shard, &items));
            }
        }
        // Four billion shards: the first 40 get one item each, the rest none, at once.
        let all = Shard::new(0, 4_000_000_000).unwrap();
        assert_eq!(all.select(&items).len(), 1);
        let last = Shard::new(3_999_999_999, 4_000_000_000).unwrap();
        assert!(last.select(&items).is_empty());
        assert!(Shard::parse("0/4000000000").is_ok());
        assert!(Shard::parse("0/4294967296").is_err());
        let slurm = |pairs: Vec<(&'static str, String)>| {
            move |k: &str| {
                pairs
                    .iter()
                    .find(|(n, _)| *n == k)
                    .map(|(_, v)| OsString::from(v))
            }
        };
        let max = Shard::from_env(
            slurm(vec![
                ("SLURM_ARRAY_TASK_ID", "7".into()),
                ("SLURM_ARRAY_TASK_COUNT", u32::MAX.to_string()),
            ]),
            None,
        )
        .unwrap()
        .unwrap();
        assert_eq!(max.select(&items).len(), 1);
        let above = Shard::from_env(
            slurm(vec![
                ("SLURM_ARRAY_TASK_ID", "7".into()),
                (
                    "SLURM_ARRAY_TASK_COUNT",
                    (u64::from(u32::MAX) + 1).to_string(),
                ),
            ]),
            None,
        );
        assert!(above.unwrap_err().to_string().contains("above"));
    }

    #[test]
    fn shards_come_from_flags_slurm_and_kubernetes() {
        assert_eq!(Shard::parse("1/4").unwrap(), Shard { index: 1, count: 4 });
        for bad in ["4/4", "1/0", "x/2", "3", "-1/2"] {
            assert!(Shard::parse(bad).is_err(), "{bad}");
        }
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |k: &str| {
                pairs
                    .iter()
                    .find(|(n, _)| *n == k)
                    .map(|(_, v)| OsString::from(v))
            }
        };
        let slurm = env(&[
            ("SLURM_ARRAY_TASK_ID", "3"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
        ]);
        assert_eq!(
            Shard::from_env(slurm, None).unwrap(),
            Some(Shard { index: 3, count: 4 })
        );
        // --array=1-4: ids start at 1.
        let from_one = env(&[
            ("SLURM_ARRAY_TASK_ID", "1"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
            ("SLURM_ARRAY_TASK_MIN", "1"),
        ]);
        assert_eq!(
            Shard::from_env(from_one, None).unwrap(),
            Some(Shard { index: 0, count: 4 })
        );
        let k8s = env(&[("JOB_COMPLETION_INDEX", "2")]);
        assert_eq!(
            Shard::from_env(k8s, Some(3)).unwrap(),
            Some(Shard { index: 2, count: 3 })
        );
        assert!(Shard::from_env(k8s, None).is_err());
        let k8s_env = env(&[("JOB_COMPLETION_INDEX", "2"), ("V2CE_SHARDS", "5")]);
        assert_eq!(
            Shard::from_env(k8s_env, None).unwrap(),
            Some(Shard { index: 2, count: 5 })
        );
        assert_eq!(Shard::from_env(env(&[]), None).unwrap(), None);
    }

    #[test]
    fn a_shard_variable_that_is_not_utf8_is_refused_not_unset() {
        use std::os::unix::ffi::OsStringExt;
        let bad = || OsString::from_vec(vec![b'3', 0xff]);
        for (name, others) in [
            ("SLURM_ARRAY_TASK_ID", vec![("SLURM_ARRAY_TASK_COUNT", "4")]),
            ("SLURM_ARRAY_TASK_COUNT", vec![("SLURM_ARRAY_TASK_ID", "1")]),
            (
                "SLURM_ARRAY_TASK_MIN",
                vec![
                    ("SLURM_ARRAY_TASK_ID", "1"),
                    ("SLURM_ARRAY_TASK_COUNT", "4"),
                ],
            ),
            (
                "SLURM_ARRAY_TASK_STEP",
                vec![
                    ("SLURM_ARRAY_TASK_ID", "1"),
                    ("SLURM_ARRAY_TASK_COUNT", "4"),
                ],
            ),
            ("JOB_COMPLETION_INDEX", vec![("V2CE_SHARDS", "4")]),
            ("V2CE_SHARDS", vec![("JOB_COMPLETION_INDEX", "1")]),
        ] {
            let var = |k: &str| {
                if k == name {
                    return Some(bad());
                }
                others
                    .iter()
                    .find(|(n, _)| *n == k)
                    .map(|(_, v)| OsString::from(v))
            };
            let err = Shard::from_env(var, None).unwrap_err().to_string();
            assert!(
                err.contains(name) && err.contains("not UTF-8"),
                "{name}: {err}"
            );
        }
    }
}
