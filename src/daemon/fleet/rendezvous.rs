//! Rendezvous (highest-random-weight) hashing (Thaler and Ravishankar, "Using name-based
//! mappings to increase hit rates", IEEE/ACM Trans. Networking 6(1), 1998): each structure
//! goes to the live member whose weight `w(member, structure)` is highest. Every daemon
//! that sees the same members computes the same owner, with no coordinator; when a member
//! leaves, only its own structures move (each to the member with its next-highest weight),
//! and when it comes back exactly those structures return to it.
//!
//! The weight is the first 8 bytes of SHA-256 over the member id, a zero byte and the
//! structure name: fixed by this crate, so daemons of different builds and machines agree.

use sha2::{Digest, Sha256};

/// The weight of `member` for `structure` (module docs).
pub fn weight(member: &str, structure: &str) -> u64 {
    let mut h = Sha256::new();
    h.update(member.as_bytes());
    h.update([0u8]);
    h.update(structure.as_bytes());
    let d = h.finalize();
    u64::from_be_bytes(d[..8].try_into().expect("a SHA-256 digest has 32 bytes"))
}

/// The owner of `structure` among `members`: the highest weight, ties (never seen in
/// practice) to the greater id. `None` when there is no member.
pub fn owner<'a>(members: impl IntoIterator<Item = &'a str>, structure: &str) -> Option<&'a str> {
    members
        .into_iter()
        .max_by_key(|m| (weight(m, structure), *m))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    fn names(prefix: &str, n: usize) -> Vec<String> {
        (0..n).map(|i| format!("{prefix}{i}")).collect()
    }

    fn assign<'a>(members: &'a [String], structures: &[String]) -> BTreeMap<String, &'a str> {
        structures
            .iter()
            .map(|s| {
                let o = owner(members.iter().map(String::as_str), s).unwrap();
                (s.clone(), o)
            })
            .collect()
    }

    #[test]
    fn the_owner_does_not_depend_on_the_order_members_are_seen_in() {
        let mut m = names("box-", 5);
        let s = names("bridge-", 40);
        let a = assign(&m, &s).into_iter().map(|(k, v)| (k, v.to_string()));
        let a: BTreeMap<_, _> = a.collect();
        m.reverse();
        let b: BTreeMap<_, _> = assign(&m, &s)
            .into_iter()
            .map(|(k, v)| (k, v.to_string()))
            .collect();
        assert_eq!(a, b);
        assert_eq!(owner(std::iter::empty(), "bridge-0"), None);
    }

    /// Removing a member moves its structures only, and adding it back restores the
    /// assignment exactly: the property the fleet's takeovers and hand-backs rely on.
    #[test]
    fn a_leaving_member_moves_only_its_own_structures() {
        let m = names("box-", 3);
        let s = names("s", 300);
        let before = assign(&m, &s);
        let lost = m[1].clone();
        let survivors: Vec<String> = m.iter().filter(|x| **x != lost).cloned().collect();
        let after = assign(&survivors, &s);
        for k in &s {
            if before[k] != lost {
                assert_eq!(before[k], after[k], "{k} moved though its owner stayed");
            } else {
                assert_ne!(after[k], lost);
            }
        }
        assert_eq!(assign(&m, &s), before);
    }

    /// 3 members and 3,000 structures: each member's share is within 3.3 standard
    /// deviations of the binomial count (1000 ± 26): the hash spreads the load.
    #[test]
    fn structures_spread_evenly_over_members() {
        let m = names("daemon-", 3);
        let s = names("structure-", 3000);
        let a = assign(&m, &s);
        for member in &m {
            let n = a.values().filter(|o| **o == member.as_str()).count() as f64;
            let sd = (3000.0_f64 * (1.0 / 3.0) * (2.0 / 3.0)).sqrt();
            assert!((n - 1000.0).abs() < 3.3 * sd, "{member}: {n} of 3000");
        }
    }

    /// The weights are pinned (values from Python's hashlib): a change of the hash would
    /// move every structure of a running fleet when the first box is upgraded.
    #[test]
    fn weights_are_fixed_across_builds() {
        assert_eq!(weight("a", "b"), 0x59b2_71ae_1bbc_b1d3);
        assert_eq!(weight("box-1", "bridge-7"), 0x40b1_660a_0df1_3ebb);
        assert_ne!(weight("a", "b"), weight("b", "a"));
    }
}
