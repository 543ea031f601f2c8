//! Shards: one heavy job (`gonio sim btf`, `gonio compress --method pvmf`) split by views
//! into `N` independent processes, and the checks that put the parts back together
//! (`gonio merge`, `merge.rs`).
//!
//! `--shard I/N` is 1-based (`1/4` … `4/4`, like a Slurm array `--array=1-4`). Shard `I`
//! takes the contiguous view range `[(I−1)·V/N, I·V/N)` of the `V` views in canonical
//! order, so the shards cover every view exactly once and each part knows its range from
//! `V` alone. Every part records [`ShardInfo`] (in a dataset's `manifest.json`
//! `extra.shard`, in a `.gbtf` header's `source.shard`), which is what lets a merge refuse
//! missing, duplicate, overlapping or mismatched parts by name.

use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::path::PathBuf;

/// One shard of `count`: `index` is 1-based.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

/// Most shards a job may be split into (a Slurm array's usual `MaxArraySize` is 1001).
pub const MAX_SHARDS: usize = 10_000;

const VALID_FORM: &str = "the valid form is I/N with 1 ≤ I ≤ N, e.g. --shard 1/4 … --shard 4/4";

impl std::str::FromStr for Shard {
    type Err = String;
    fn from_str(s: &str) -> Result<Shard, String> {
        let (i, n) = s
            .split_once('/')
            .ok_or_else(|| format!("`{s}` is not I/N; {VALID_FORM}"))?;
        let num = |x: &str, what: &str| {
            x.trim()
                .parse::<usize>()
                .map_err(|_| format!("`{s}`: {what} `{x}` is not a whole number; {VALID_FORM}"))
        };
        let (index, count) = (num(i, "I")?, num(n, "N")?);
        if count == 0 {
            return Err(format!("`{s}`: N must be at least 1; {VALID_FORM}"));
        }
        if count > MAX_SHARDS {
            return Err(format!("`{s}`: at most {MAX_SHARDS} shards"));
        }
        if index == 0 || index > count {
            return Err(format!("`{s}`: shard I = {index} is outside 1..={count}; {VALID_FORM}"));
        }
        Ok(Shard { index, count })
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

impl Shard {
    /// The views of this shard among `n_views` (contiguous, possibly empty when there are
    /// more shards than views; see [`Shard::check_views`]).
    pub fn views(&self, n_views: usize) -> Range<usize> {
        let at = |k: usize| k * n_views / self.count;
        at(self.index - 1)..at(self.index)
    }

    /// Refuse a split with empty shards (more shards than views).
    pub fn check_views(&self, n_views: usize) -> Result<(), String> {
        if self.count > n_views {
            return Err(format!(
                "--shard {self}: {n_views} views cannot be split into {} shards (at most {n_views})",
                self.count
            ));
        }
        Ok(())
    }

    /// What a part records about itself.
    pub fn info(&self, n_views: usize) -> ShardInfo {
        let r = self.views(n_views);
        ShardInfo {
            index: self.index,
            count: self.count,
            first_view: r.start,
            end_view: r.end,
            views_total: n_views,
        }
    }
}

/// The shard a part holds, as stored in the part.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ShardInfo {
    /// 1-based shard number.
    pub index: usize,
    pub count: usize,
    /// The part's views: `first_view..end_view` (canonical view indices).
    pub first_view: usize,
    pub end_view: usize,
    /// Views of the whole job.
    pub views_total: usize,
}

impl ShardInfo {
    pub fn shard(&self) -> Shard {
        Shard {
            index: self.index,
            count: self.count,
        }
    }
    fn label(&self) -> String {
        format!(
            "shard {}/{} (views {}..{})",
            self.index, self.count, self.first_view, self.end_view
        )
    }
}

/// Why a set of parts cannot be merged. Every variant names the parts involved.
#[derive(Debug, thiserror::Error)]
pub enum ShardError {
    #[error("{path}: not a shard part ({reason}); give the outputs of runs with --shard I/N")]
    NotAPart { path: PathBuf, reason: String },
    #[error("no parts given: name every part (e.g. parts/part-*)")]
    NoParts,
    #[error(
        "missing {}: {} of {count} shard(s) given. Re-run the missing shard(s) with --shard I/{count} \
         and merge again",
        missing.join(", "), count - missing.len()
    )]
    Missing { count: usize, missing: Vec<String> },
    #[error("{label} given twice: {first} and {second}; keep one of them")]
    Duplicate {
        label: String,
        first: PathBuf,
        second: PathBuf,
    },
    #[error(
        "{path} is shard {index}/{count} but {first} is shard {first_index}/{first_count}: parts of one \
         job have the same N"
    )]
    CountMismatch {
        path: PathBuf,
        index: usize,
        count: usize,
        first: PathBuf,
        first_index: usize,
        first_count: usize,
    },
    #[error("{path}: {label} does not match the split of {views_total} views into {count} (a different job or gonio)")]
    BadRange {
        path: PathBuf,
        label: String,
        views_total: usize,
        count: usize,
    },
    #[error("shards {given} of {count} are not a group for a partial merge: {why}")]
    BadGroup { count: usize, given: String, why: String },
    #[error("{path} and {first} are parts of different jobs: {field} differs ({detail})")]
    Mismatch {
        path: PathBuf,
        first: PathBuf,
        field: String,
        detail: String,
    },
}

/// Check that `parts` (path, recorded shard) are exactly the shards `1..=N` of one split,
/// and return their positions in shard order.
pub fn check_complete(parts: &[(PathBuf, ShardInfo)]) -> Result<Vec<usize>, ShardError> {
    let (slot, count, views_total) = slots(parts)?;
    let missing: Vec<String> = slot
        .iter()
        .enumerate()
        .filter(|(_, s)| s.is_none())
        .map(|(i, _)| Shard { index: i + 1, count }.info(views_total).label())
        .collect();
    if !missing.is_empty() {
        return Err(ShardError::Missing { count, missing });
    }
    Ok(slot.into_iter().map(|s| s.expect("checked above")).collect())
}

/// Check that `parts` are one **group** of a split of N: the `m` consecutive shards
/// `(g−1)·m + 1 ..= g·m`, with `m` dividing N. Their views are then exactly shard `g` of
/// `N / m` (`⌊(g−1)·m·V/N⌋ = ⌊(g−1)·V/(N/m)⌋`), so a partial merge of a group is a part
/// of the coarser split, and merges can form a tree. Returns the parts' positions in
/// shard order and the group's shard.
pub fn check_group(parts: &[(PathBuf, ShardInfo)]) -> Result<(Vec<usize>, Shard), ShardError> {
    let (slot, count, views_total) = slots(parts)?;
    let given: Vec<usize> = (0..count).filter(|&i| slot[i].is_some()).collect();
    let (lo, m) = (given[0], given.len());
    let bad = |why: String| ShardError::BadGroup {
        count,
        given: format!("{}..={}", lo + 1, given[m - 1] + 1),
        why,
    };
    if given[m - 1] - lo + 1 != m {
        let gap = (lo..given[m - 1]).find(|i| slot[*i].is_none()).unwrap_or(lo);
        return Err(bad(format!("shard {}/{count} is missing from the run", gap + 1)));
    }
    if count % m != 0 || lo % m != 0 {
        return Err(bad(format!(
            "a group is m consecutive shards starting after a multiple of m, with m dividing {count}              (for m = {m}: {})",
            if count % m == 0 {
                format!("shards {}..={}", lo / m * m + 1, lo / m * m + m)
            } else {
                format!("{m} does not divide {count}")
            }
        )));
    }
    let group = Shard {
        index: lo / m + 1,
        count: count / m,
    };
    debug_assert_eq!(
        group.views(views_total).start,
        Shard { index: lo + 1, count }.views(views_total).start
    );
    Ok((slot.into_iter().flatten().collect(), group))
}

/// Every part's slot among the shards `1..=N` of one split (checked: the same N and
/// views, a range that matches the split, no shard twice), with N and the views.
fn slots(parts: &[(PathBuf, ShardInfo)]) -> Result<(Vec<Option<usize>>, usize, usize), ShardError> {
    let Some((first_path, first)) = parts.first() else {
        return Err(ShardError::NoParts);
    };
    let count = first.count;
    let mut slot: Vec<Option<usize>> = vec![None; count];
    for (k, (path, info)) in parts.iter().enumerate() {
        if info.count != count || info.views_total != first.views_total {
            return Err(ShardError::CountMismatch {
                path: path.clone(),
                index: info.index,
                count: info.count,
                first: first_path.clone(),
                first_index: first.index,
                first_count: first.count,
            });
        }
        let expect = info.shard().info(info.views_total);
        if info.index == 0 || info.index > count || expect != *info {
            return Err(ShardError::BadRange {
                path: path.clone(),
                label: info.label(),
                views_total: info.views_total,
                count,
            });
        }
        if let Some(prev) = slot[info.index - 1] {
            return Err(ShardError::Duplicate {
                label: info.label(),
                first: parts[prev].0.clone(),
                second: path.clone(),
            });
        }
        slot[info.index - 1] = Some(k);
    }
    Ok((slot, count, first.views_total))
}

/// The first top-level key (sorted) whose value differs between two JSON objects, with
/// both values shortened; `None` when they are equal.
pub fn first_difference(a: &serde_json::Value, b: &serde_json::Value) -> Option<(String, String)> {
    if a == b {
        return None;
    }
    let short = |v: Option<&serde_json::Value>| {
        let s = v.map(|v| v.to_string()).unwrap_or_else(|| "absent".into());
        if s.chars().count() > 80 {
            format!("{}…", s.chars().take(80).collect::<String>())
        } else {
            s
        }
    };
    match (a.as_object(), b.as_object()) {
        (Some(x), Some(y)) => {
            let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
            keys.into_iter()
                .find(|k| x.get(*k) != y.get(*k))
                .map(|k| (k.clone(), format!("{} vs {}", short(x.get(k)), short(y.get(k)))))
        }
        _ => Some(("value".into(), format!("{} vs {}", short(Some(a)), short(Some(b))))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parse_accepts_i_of_n_and_refuses_the_rest_with_the_valid_form() {
        assert_eq!("2/4".parse::<Shard>().unwrap(), Shard { index: 2, count: 4 });
        for bad in ["3/2", "0/0", "0/3", "1/0", "x/2", "2", "-1/2", "1/99999"] {
            let e = bad.parse::<Shard>().unwrap_err();
            assert!(e.contains(bad), "{bad}: {e}");
            if bad != "1/99999" {
                assert!(e.contains("I/N"), "{bad}: {e}");
            }
        }
    }

    #[test]
    fn shards_cover_every_view_once() {
        for n_views in [1usize, 7, 81, 151] {
            for count in 1..=n_views.min(9) {
                let mut next = 0;
                for index in 1..=count {
                    let r = Shard { index, count }.views(n_views);
                    assert_eq!(r.start, next);
                    assert!(!r.is_empty());
                    next = r.end;
                }
                assert_eq!(next, n_views);
            }
        }
        assert!(Shard { index: 1, count: 5 }.check_views(4).is_err());
    }

    fn parts(spec: &[(usize, usize)], views: usize) -> Vec<(PathBuf, ShardInfo)> {
        spec.iter()
            .map(|&(i, n)| {
                (
                    PathBuf::from(format!("part-{i}")),
                    Shard { index: i, count: n }.info(views),
                )
            })
            .collect()
    }

    #[test]
    fn merge_check_names_missing_duplicate_and_mismatched_parts() {
        assert_eq!(
            check_complete(&parts(&[(2, 3), (1, 3), (3, 3)], 9)).unwrap(),
            vec![1, 0, 2]
        );
        let e = check_complete(&parts(&[(1, 3), (3, 3)], 9)).unwrap_err().to_string();
        assert!(e.contains("missing shard 2/3 (views 3..6)"), "{e}");
        let e = check_complete(&parts(&[(1, 2), (1, 2), (2, 2)], 9))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("shard 1/2") && e.contains("twice") && e.contains("part-1"),
            "{e}"
        );
        let e = check_complete(&parts(&[(1, 2), (2, 3)], 9)).unwrap_err().to_string();
        assert!(e.contains("part-2") && e.contains("same N"), "{e}");
        // A part claiming another range (overlap with a neighbour) is refused.
        let mut p = parts(&[(1, 2), (2, 2)], 9);
        p[1].1.first_view = 3;
        let e = check_complete(&p).unwrap_err().to_string();
        assert!(e.contains("part-2") && e.contains("views 3..9"), "{e}");
        assert!(matches!(check_complete(&[]), Err(ShardError::NoParts)));
    }

    /// A group of m consecutive shards starting after a multiple of m (m dividing N) covers
    /// exactly the views of shard g of N/m, for every view count; anything else is refused.
    #[test]
    fn groups_are_shards_of_the_coarser_split() {
        for views in [5, 7, 12, 151] {
            for (n, m) in [(4, 2), (6, 3), (6, 2), (8, 4), (8, 8), (3, 1)] {
                if n > views {
                    continue;
                }
                for g in 0..n / m {
                    let spec: Vec<(usize, usize)> = (g * m + 1..=g * m + m).rev().map(|i| (i, n)).collect();
                    let ps = parts(&spec, views);
                    let (order, group) = check_group(&ps).unwrap();
                    assert_eq!(
                        group,
                        Shard {
                            index: g + 1,
                            count: n / m
                        }
                    );
                    let first = &ps[order[0]].1;
                    let last = &ps[order[m - 1]].1;
                    assert_eq!(
                        group.views(views),
                        first.first_view..last.end_view,
                        "views {views}, {n}/{m}, group {g}"
                    );
                }
            }
        }
        let e = check_group(&parts(&[(2, 4), (3, 4)], 8)).unwrap_err().to_string();
        assert!(e.contains("shards 1..=2"), "{e}");
        let e = check_group(&parts(&[(1, 4), (3, 4)], 8)).unwrap_err().to_string();
        assert!(e.contains("shard 2/4 is missing"), "{e}");
        let e = check_group(&parts(&[(1, 4), (2, 4), (3, 4)], 8))
            .unwrap_err()
            .to_string();
        assert!(e.contains("3 does not divide 4"), "{e}");
        assert!(check_group(&parts(&[(1, 4), (1, 4)], 8)).is_err());
    }
}
