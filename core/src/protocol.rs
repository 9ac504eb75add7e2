//! Evaluation protocols: which trials a trained estimator fits on and which it
//! is scored on, fold by fold.
//!
//! Every protocol returns folds `(train, test)` of trial indices such that
//! every trial is tested exactly once (hold-out: the held-out share only) and
//! **no fold's training set contains one of its test trials** (the test in
//! this module checks both for every protocol). A model-based estimator (WSS)
//! gets one fold with no training trial and every trial to test (under a
//! hold-out: the held-out trials, so every estimator is scored on the same
//! trials; the runtime then passes on only the scored trials).
//!
//! * `leave_one_trial_out` (the paper's): fold `f` tests the `f`-th distinct
//!   repetition (`group`) of every class and trains on every other one.
//! * `k_fold`: stratified, seeded `k`-fold: within each class (true angle and
//!   stimulus) the trials are shuffled (ChaCha8 from `derive_seed(seed,
//!   ["k_fold"])`) and dealt round-robin to folds, continuing where the
//!   previous class stopped, so folds differ in size by at most one and every
//!   class is spread evenly. `k` in `[2, trials]`.
//! * `hold_out`: one fold; within each class, `round(test_share × n_class)`
//!   trials (at least one when `n_class ≥ 2`, never all) drawn by a seeded
//!   shuffle are tested, the rest train; trials not held out are not scored.
//! * `leave_one_condition_out`: fold per distinct value of a label `key`:
//!   `group` (the repetition: the same folds as leave-one-trial-out),
//!   `angle` (leave one class out: the test class is never seen in training),
//!   `stimulus`, or any key of the trials' `conditions` (a scene's
//!   `conditions` table sets `condition`; a label file's extra keys set
//!   theirs): fold `v` tests every trial recorded under value `v` and trains on
//!   every other condition, so no estimator sees the test condition in training.
//! * `train_test`: one fold for a shift: trained estimators fit on every trial
//!   whose `key` (as above) is one of the `train` values and are scored on every
//!   other trial; model-based estimators are scored on those same test trials
//!   and see no training trial (the paper's case for WSS: nothing to retrain
//!   when the conditions change). Only the test trials are scored.

use crate::payload::{Item, TrialMeta};
use crate::stage::derive_seed;
use rand::seq::SliceRandom;
use rand_chacha::rand_core::SeedableRng;
use serde::{Deserialize, Serialize};

/// How trained estimators are evaluated (the graph's `[run] protocol`).
///
/// In TOML: `protocol = "leave_one_trial_out"`, or a table naming one
/// protocol: `protocol = { k_fold = { k = 5, seed = 1 } }`,
/// `protocol = { hold_out = { test_share = 0.3, seed = 1 } }`,
/// `protocol = { leave_one_condition_out = { key = "angle" } }`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Protocol {
    /// Leave-one-trial-out, as in the paper: fold `f` tests the `f`-th
    /// repetition of every class and trains on every other repetition.
    /// Model-based estimators (WSS) ignore the training part.
    #[default]
    LeaveOneTrialOut,
    /// Stratified, seeded k-fold cross-validation.
    KFold {
        /// Number of folds, at least 2 and at most the number of trials.
        k: usize,
        /// Seed of the shuffle. Default 0.
        #[serde(default)]
        seed: u64,
    },
    /// One stratified, seeded split: a share of each class is tested.
    HoldOut {
        /// Share of each class's trials tested, in (0, 1).
        test_share: f64,
        /// Seed of the shuffle. Default 0.
        #[serde(default)]
        seed: u64,
    },
    /// One fold per distinct value of a label key: "group", "angle",
    /// "stimulus" or a key of the trials' `conditions`.
    LeaveOneConditionOut {
        /// The label key.
        key: String,
    },
    /// Train on the trials whose label `key` is one of `train`, score every
    /// other trial (one fold; model-based estimators see only the test trials).
    TrainTest {
        /// The label key: "group", "angle", "stimulus" or a key of the trials'
        /// `conditions` (e.g. "condition").
        key: String,
        /// The values of `key` trained on; every other value is tested.
        /// Strings or numbers (`train = [0, 1]` for groups); for `angle`,
        /// degrees (`train = [30, 45]`).
        #[serde(deserialize_with = "label_strings")]
        train: Vec<String>,
    },
}

/// `train_test`'s values as strings: a number is written as TOML would
/// show it (`0`, `32.5`), so `train = [0]` names group "0".
fn label_strings<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<String>, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Value {
        Text(String),
        Int(i64),
        Float(f64),
    }
    Ok(Vec::<Value>::deserialize(d)?
        .into_iter()
        .map(|v| match v {
            Value::Text(s) => s,
            Value::Int(i) => i.to_string(),
            Value::Float(f) => crate::fmt_num(f),
        })
        .collect())
}

/// An angle in whole micro-degrees: how the `angle` label and the
/// stratification compare angles (exact, where degrees in `f64` may differ
/// in the last bit).
fn micro_degrees(a: f64) -> i64 {
    (a * 1e6).round() as i64
}

/// A trial's `angle` label value (micro-degrees, see [`label_value`]) for
/// a `train` value given in degrees; other keys' values, and values that
/// are not numbers, unchanged.
fn train_value(key: &str, v: &str) -> String {
    match (key, v.trim().parse::<f64>()) {
        ("angle", Ok(a)) if a.is_finite() => micro_degrees(a).to_string(),
        _ => v.to_string(),
    }
}

/// One fold: trial indices to train on and to test.
pub type Fold = (Vec<usize>, Vec<usize>);

/// The label keys every trial has; `leave_one_condition_out` and
/// `train_test` also accept any key of the trials' `conditions`.
pub const CONDITION_KEYS: [&str; 3] = ["group", "angle", "stimulus"];

/// The value of label `key` for a trial: a built-in key ([`CONDITION_KEYS`])
/// or one of its `conditions`.
fn label_value(m: &TrialMeta, key: &str) -> Option<String> {
    match key {
        "group" => Some(m.group.to_string()),
        "angle" => Some(
            m.label
                .angle_deg
                .map_or("none".into(), |a| micro_degrees(a).to_string()),
        ),
        "stimulus" => Some(format!("{:?}", m.label.stimulus)),
        _ => m.conditions.get(key).cloned(),
    }
}

/// Every trial's value of `key`, or an error naming the key, a trial without
/// it and the condition keys the trials do have.
fn label_values(metas: &[&TrialMeta], key: &str, protocol: &str) -> Result<Vec<String>, String> {
    metas
        .iter()
        .map(|m| {
            label_value(m, key).ok_or_else(|| {
                let mut have: Vec<&str> = CONDITION_KEYS.to_vec();
                have.extend(m.conditions.keys().map(String::as_str));
                format!(
                    "protocol.{protocol}.key: trial `{}` has no label `{key}`; its labels are {}",
                    m.trial_id,
                    have.iter()
                        .map(|k| format!("`{k}`"))
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            })
        })
        .collect()
}

impl Protocol {
    /// Checks the protocol's values, naming the key.
    pub fn check(&self) -> Result<(), String> {
        match self {
            Protocol::LeaveOneTrialOut => Ok(()),
            Protocol::KFold { k, .. } if *k < 2 => Err(format!("protocol.k_fold.k: must be at least 2, got {k}")),
            Protocol::KFold { .. } => Ok(()),
            Protocol::HoldOut { test_share, .. } if !(*test_share > 0.0 && *test_share < 1.0) => Err(format!(
                "protocol.hold_out.test_share: must lie in (0, 1), got {}",
                crate::fmt_num(*test_share)
            )),
            Protocol::HoldOut { .. } => Ok(()),
            Protocol::LeaveOneConditionOut { key } if key.trim().is_empty() => Err(
                "protocol.leave_one_condition_out.key: empty; name a label (\"group\", \"angle\", \"stimulus\" or a condition key)".into(),
            ),
            Protocol::LeaveOneConditionOut { .. } => Ok(()),
            Protocol::TrainTest { key, .. } if key.trim().is_empty() => Err(
                "protocol.train_test.key: empty; name a label (\"group\", \"angle\", \"stimulus\" or a condition key)".into(),
            ),
            Protocol::TrainTest { train, .. } if train.is_empty() => {
                Err("protocol.train_test.train: no value to train on".into())
            }
            Protocol::TrainTest { .. } => Ok(()),
        }
    }

    /// The protocol's name as a graph writes it (`hold_out`, ...).
    pub fn name(&self) -> &'static str {
        match self {
            Protocol::LeaveOneTrialOut => "leave_one_trial_out",
            Protocol::KFold { .. } => "k_fold",
            Protocol::HoldOut { .. } => "hold_out",
            Protocol::LeaveOneConditionOut { .. } => "leave_one_condition_out",
            Protocol::TrainTest { .. } => "train_test",
        }
    }

    /// True when only some trials are scored (hold-out, train/test): one fold
    /// by design, and the runtime passes on only the scored trials.
    pub fn scores_a_subset(&self) -> bool {
        matches!(self, Protocol::HoldOut { .. } | Protocol::TrainTest { .. })
    }
}

/// A trial's class for stratification: stimulus and angle (to 1e-6 degree).
fn class_key(m: &TrialMeta) -> (String, i64) {
    let l = &m.label;
    (
        format!("{:?}", l.stimulus),
        l.angle_deg.map_or(i64::MIN, micro_degrees),
    )
}

/// Trial indices grouped by class, classes in order of first appearance.
fn by_class(metas: &[&TrialMeta]) -> Vec<Vec<usize>> {
    let mut keys: Vec<(String, i64)> = Vec::new();
    let mut groups: Vec<Vec<usize>> = Vec::new();
    for (i, m) in metas.iter().enumerate() {
        let k = class_key(m);
        match keys.iter().position(|x| *x == k) {
            Some(j) => groups[j].push(i),
            None => {
                keys.push(k);
                groups.push(vec![i]);
            }
        }
    }
    groups
}

/// Folds of `protocol` over `items`: `(train, test)` index lists. A
/// model-based estimator (`trained == false`) gets one fold testing every
/// trial. Errors (naming the key) on an invalid protocol or one the data
/// cannot satisfy (more folds than trials).
pub fn folds(trained: bool, protocol: &Protocol, items: &[Item]) -> Result<Vec<Fold>, String> {
    let metas: Vec<&TrialMeta> = items.iter().map(|it| &*it.meta).collect();
    folds_of(trained, protocol, &metas)
}

/// [`folds`] from the trials' metadata alone: a protocol reads labels,
/// groups and conditions, never data, so the folds are known before any
/// stage has run (the depth-first chains use this to skip the trials a
/// hold-out does not score).
pub fn folds_of(trained: bool, protocol: &Protocol, metas: &[&TrialMeta]) -> Result<Vec<Fold>, String> {
    protocol.check()?;
    if !trained {
        // A model-based estimator is scored on every trial a trained one is:
        // all of them, except under a hold-out (the held-out trials only).
        let test = if protocol.scores_a_subset() {
            folds_of(true, protocol, metas)?.remove(0).1
        } else {
            (0..metas.len()).collect()
        };
        return Ok(vec![(Vec::new(), test)]);
    }
    let n = metas.len();
    let partition = |fold_of: &dyn Fn(usize) -> usize, n_folds: usize| -> Vec<Fold> {
        (0..n_folds)
            .map(|f| {
                let (test, train): (Vec<usize>, Vec<usize>) = (0..n).partition(|&t| fold_of(t) == f);
                (train, test)
            })
            .filter(|(_, test)| !test.is_empty())
            .collect()
    };
    Ok(match protocol {
        Protocol::LeaveOneTrialOut => condition_folds(label_values(metas, "group", "leave_one_trial_out")?),
        Protocol::LeaveOneConditionOut { key } => {
            condition_folds(label_values(metas, key, "leave_one_condition_out")?)
        }
        Protocol::TrainTest { key, train } => {
            let values = label_values(metas, key, "train_test")?;
            let wanted: Vec<String> = train.iter().map(|v| train_value(key, v)).collect();
            let (tr, te): (Vec<usize>, Vec<usize>) = (0..n).partition(|&t| wanted.contains(&values[t]));
            if tr.is_empty() {
                // Angles as degrees, as `train` takes them.
                let mut seen: Vec<String> = if key == "angle" {
                    values
                        .iter()
                        .map(|v| v.parse::<f64>().map_or(v.clone(), |m| crate::fmt_num(m / 1e6)))
                        .collect()
                } else {
                    values.clone()
                };
                seen.sort();
                seen.dedup();
                return Err(format!(
                    "protocol.train_test.train: no trial has `{key}` in {train:?}; the trials' values are {seen:?}"
                ));
            }
            if te.is_empty() {
                return Err(format!(
                    "protocol.train_test.train: every trial has `{key}` in {train:?}, so none is left to test"
                ));
            }
            vec![(tr, te)]
        }
        Protocol::KFold { k, seed } => {
            if *k > n {
                return Err(format!(
                    "protocol.k_fold.k: {k} folds but only {n} trials; use at most {n}"
                ));
            }
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(derive_seed(*seed, &["k_fold"]));
            let mut fold = vec![0usize; n];
            let mut next = 0;
            for mut class in by_class(metas) {
                class.shuffle(&mut rng);
                for t in class {
                    fold[t] = next % k;
                    next += 1;
                }
            }
            partition(&|t| fold[t], *k)
        }
        Protocol::HoldOut { test_share, seed } => {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(derive_seed(*seed, &["hold_out"]));
            let (mut train, mut test) = (Vec::new(), Vec::new());
            for mut class in by_class(metas) {
                class.shuffle(&mut rng);
                let m = class.len();
                let mut n_test = (test_share * m as f64).round() as usize;
                if m >= 2 {
                    n_test = n_test.clamp(1, m - 1);
                } else {
                    n_test = 0;
                }
                test.extend_from_slice(&class[..n_test]);
                train.extend_from_slice(&class[n_test..]);
            }
            train.sort_unstable();
            test.sort_unstable();
            if test.is_empty() {
                return Err("protocol.hold_out: no class has two trials, so nothing can be held out".into());
            }
            vec![(train, test)]
        }
    })
}

/// One fold per distinct value of `value` (in sorted order): test that value,
/// train on the rest.
fn condition_folds(values: Vec<String>) -> Vec<Fold> {
    let mut distinct = values.clone();
    distinct.sort_by(|a, b| match (a.parse::<i64>(), b.parse::<i64>()) {
        (Ok(x), Ok(y)) => x.cmp(&y),
        _ => a.cmp(b),
    });
    distinct.dedup();
    distinct
        .iter()
        .map(|v| {
            let (test, train): (Vec<usize>, Vec<usize>) = (0..values.len()).partition(|&t| values[t] == *v);
            (train, test)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::payload::{Estimate, Label, Payload, Stimulus, TrialMeta};
    use proptest::prelude::*;
    use std::sync::Arc;

    fn item(group: usize, angle: f64, id: &str) -> Item {
        Item {
            meta: Arc::new(TrialMeta {
                trial_id: id.into(),
                group,
                label: Label {
                    stimulus: Stimulus::Edge,
                    angle_deg: Some(angle),
                },
                ..TrialMeta::default()
            }),
            payload: Payload::from(Estimate::default()),
        }
    }

    fn data(classes: usize, reps: usize) -> Vec<Item> {
        (0..classes * reps)
            .map(|t| item(t % reps, 10.0 + 5.0 * (t / reps) as f64, &format!("t{t}")))
            .collect()
    }

    fn all() -> Vec<Protocol> {
        vec![
            Protocol::LeaveOneTrialOut,
            Protocol::KFold { k: 3, seed: 7 },
            Protocol::KFold { k: 5, seed: 1 },
            Protocol::HoldOut {
                test_share: 0.3,
                seed: 2,
            },
            Protocol::LeaveOneConditionOut { key: "group".into() },
            Protocol::LeaveOneConditionOut { key: "angle".into() },
            Protocol::LeaveOneConditionOut {
                key: "stimulus".into(),
            },
            Protocol::TrainTest {
                key: "group".into(),
                train: vec!["0".into(), "2".into()],
            },
        ]
    }

    /// The property every protocol owes: no test trial reaches a fit, and no
    /// trial is tested twice; all but hold-out test every trial.
    fn check_no_leak(p: &Protocol, items: &[Item]) -> Result<(), TestCaseError> {
        let f = folds(true, p, items).map_err(TestCaseError::fail)?;
        let mut tested = vec![0; items.len()];
        for (train, test) in &f {
            prop_assert!(!test.is_empty());
            for t in test {
                prop_assert!(!train.contains(t), "{p:?}: test trial {t} in training");
                tested[*t] += 1;
            }
            // Trial ids too: a duplicate id in training would leak as well.
            for t in test {
                prop_assert!(train
                    .iter()
                    .all(|&r| items[r].meta.trial_id != items[*t].meta.trial_id));
            }
        }
        prop_assert!(tested.iter().all(|&c| c <= 1), "{p:?}: a trial tested twice");
        if !p.scores_a_subset() {
            prop_assert!(tested.iter().all(|&c| c == 1), "{p:?}: a trial never tested");
        }
        Ok(())
    }

    #[test]
    fn leave_one_trial_out_never_trains_on_a_test_trial() {
        let items: Vec<Item> = (0..12).map(|t| item(t % 4, 45.0, &format!("t{t}"))).collect();
        let f = folds(true, &Protocol::LeaveOneTrialOut, &items).unwrap();
        assert_eq!(f.len(), 4);
        for (train, test) in &f {
            assert_eq!(test.len(), 3);
            assert_eq!(train.len() + test.len(), items.len());
        }
        let m = folds(false, &Protocol::LeaveOneTrialOut, &items).unwrap();
        assert_eq!(m.len(), 1);
        assert!(m[0].0.is_empty());
    }

    #[test]
    fn k_fold_is_stratified_balanced_and_seeded() {
        let items = data(17, 10);
        let p = Protocol::KFold { k: 5, seed: 3 };
        let f = folds(true, &p, &items).unwrap();
        assert_eq!(f.len(), 5);
        for (_, test) in &f {
            assert_eq!(test.len(), 34);
            // Every class has exactly 2 of its 10 trials in each fold.
            for c in 0..17 {
                assert_eq!(test.iter().filter(|&&t| t / 10 == c).count(), 2);
            }
        }
        assert_eq!(f, folds(true, &p, &items).unwrap(), "same seed, same folds");
        assert_ne!(
            f,
            folds(true, &Protocol::KFold { k: 5, seed: 4 }, &items).unwrap()
        );
        assert!(folds(true, &Protocol::KFold { k: 171, seed: 0 }, &items).is_err());
        assert!(folds(true, &Protocol::KFold { k: 1, seed: 0 }, &items).is_err());
    }

    #[test]
    fn hold_out_tests_the_share_of_each_class() {
        let items = data(17, 10);
        let f = folds(
            true,
            &Protocol::HoldOut {
                test_share: 0.3,
                seed: 1,
            },
            &items,
        )
        .unwrap();
        assert_eq!(f.len(), 1);
        assert_eq!(f[0].1.len(), 51);
        assert_eq!(f[0].0.len(), 119);
        let bad = Protocol::HoldOut {
            test_share: 1.0,
            seed: 1,
        };
        assert!(folds(true, &bad, &items).unwrap_err().contains("test_share"));
    }

    #[test]
    fn leave_one_class_out_never_trains_on_the_test_class() {
        let items = data(4, 3);
        let f = folds(
            true,
            &Protocol::LeaveOneConditionOut { key: "angle".into() },
            &items,
        )
        .unwrap();
        assert_eq!(f.len(), 4);
        for (train, test) in &f {
            let a = items[test[0]].meta.label.angle_deg;
            assert!(train.iter().all(|&t| items[t].meta.label.angle_deg != a));
        }
        let bad = Protocol::LeaveOneConditionOut { key: "speed".into() };
        assert!(folds(true, &bad, &items).unwrap_err().contains("speed"));
    }

    #[test]
    fn protocols_read_from_toml() {
        #[derive(Deserialize)]
        struct R {
            protocol: Protocol,
        }
        let r: R = toml::from_str("protocol = \"leave_one_trial_out\"").unwrap();
        assert_eq!(r.protocol, Protocol::LeaveOneTrialOut);
        let r: R = toml::from_str("protocol = { k_fold = { k = 5, seed = 2 } }").unwrap();
        assert_eq!(r.protocol, Protocol::KFold { k: 5, seed: 2 });
    }

    #[test]
    fn train_test_takes_numbers_and_angles_in_degrees() {
        #[derive(Deserialize)]
        struct R {
            protocol: Protocol,
        }
        let read = |t: &str| toml::from_str::<R>(t).unwrap().protocol;
        // Groups as integers: the same split as the strings.
        let items = data(3, 4);
        let by_text = read("protocol = { train_test = { key = \"group\", train = [\"0\", \"1\"] } }");
        let by_number = read("protocol = { train_test = { key = \"group\", train = [0, 1] } }");
        assert_eq!(by_text, by_number);
        let f = folds(true, &by_number, &items).unwrap();
        assert_eq!(f[0].0.len(), 6);
        assert!(f[0].0.iter().all(|&t| items[t].meta.group < 2));
        // Angles in degrees (integer or not), where the label compares them
        // in micro-degrees.
        let odd: Vec<Item> = [30.0, 32.5, 45.0, 30.0, 32.5, 45.0]
            .iter()
            .enumerate()
            .map(|(i, &a)| item(i / 3, a, &format!("t{i}")))
            .collect();
        let p = read("protocol = { train_test = { key = \"angle\", train = [30, 32.5] } }");
        let f = folds(true, &p, &odd).unwrap();
        assert_eq!(f, vec![(vec![0, 1, 3, 4], vec![2, 5])]);
        // An angle no trial has: the error lists the trials' angles in degrees.
        let e = folds(
            true,
            &read("protocol = { train_test = { key = \"angle\", train = [60] } }"),
            &odd,
        )
        .unwrap_err();
        assert!(e.contains("\"32.5\"") && e.contains("\"45\""), "{e}");
    }

    proptest! {
        #[test]
        fn no_protocol_ever_lets_a_test_trial_reach_a_fit(
            classes in 1usize..8,
            reps in 1usize..8,
            which in 0usize..7,
        ) {
            let items = data(classes, reps);
            let p = &all()[which];
            match folds(true, p, &items) {
                Ok(_) => check_no_leak(p, &items)?,
                // Only a data set too small for the protocol may refuse.
                Err(e) => prop_assert!(
                    (matches!(p, Protocol::KFold { k, .. } if *k > items.len()))
                        || (matches!(p, Protocol::HoldOut { .. }) && reps < 2),
                    "{p:?}: {e}"
                ),
            }
        }
    }

    fn with_condition(mut it: Item, key: &str, value: &str) -> Item {
        let mut m = (*it.meta).clone();
        m.conditions.insert(key.into(), value.into());
        it.meta = Arc::new(m);
        it
    }

    #[test]
    fn conditions_split_folds_and_train_test_never_leaks() {
        // 3 classes x 4 reps under "slow", the same under "fast".
        let items: Vec<Item> = data(3, 4)
            .into_iter()
            .map(|it| with_condition(it, "condition", "slow"))
            .chain(data(3, 4).into_iter().enumerate().map(|(i, it)| {
                let mut it = with_condition(it, "condition", "fast");
                let mut m = (*it.meta).clone();
                m.trial_id = format!("fast{i}");
                it.meta = Arc::new(m);
                it
            }))
            .collect();
        let loco = Protocol::LeaveOneConditionOut {
            key: "condition".into(),
        };
        let f = folds(true, &loco, &items).unwrap();
        assert_eq!(f.len(), 2);
        for (train, test) in &f {
            let tc = &items[test[0]].meta.conditions["condition"];
            assert!(test.iter().all(|&t| &items[t].meta.conditions["condition"] == tc));
            assert!(train
                .iter()
                .all(|&t| &items[t].meta.conditions["condition"] != tc));
        }
        check_no_leak(&loco, &items).unwrap();
        let tt = Protocol::TrainTest {
            key: "condition".into(),
            train: vec!["slow".into()],
        };
        let f = folds(true, &tt, &items).unwrap();
        assert_eq!(f, vec![((0..12).collect(), (12..24).collect())]);
        check_no_leak(&tt, &items).unwrap();
        // Model-based estimators are scored on the same test trials only.
        assert_eq!(
            folds(false, &tt, &items).unwrap(),
            vec![(vec![], (12..24).collect())]
        );
        // A key no trial has, or a split that leaves nothing to train or to
        // test, is an error naming the key.
        let e = folds(
            true,
            &Protocol::LeaveOneConditionOut { key: "speed".into() },
            &items,
        )
        .unwrap_err();
        assert!(e.contains("no label `speed`") && e.contains("`condition`"), "{e}");
        let none = Protocol::TrainTest {
            key: "condition".into(),
            train: vec!["medium".into()],
        };
        assert!(folds(true, &none, &items).unwrap_err().contains("\"fast\""));
        let all = Protocol::TrainTest {
            key: "condition".into(),
            train: vec!["slow".into(), "fast".into()],
        };
        assert!(folds(true, &all, &items)
            .unwrap_err()
            .contains("none is left to test"));
        assert!(Protocol::TrainTest {
            key: "condition".into(),
            train: vec![]
        }
        .check()
        .is_err());
    }
}
