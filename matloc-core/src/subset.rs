//! Evenly spaced subsets, for taking `n` representative views or queries from an ordered list
//! (a survey's images are ordered along its flight lines).

/// At most `n` indices of `0..len`, evenly spaced (the centre of each of `n` equal strides);
/// all of them when `n == 0` or `n >= len`.
pub fn evenly_spaced(len: usize, n: usize) -> Vec<usize> {
    if n == 0 || n >= len {
        return (0..len).collect();
    }
    let step = len as f64 / n as f64;
    (0..n).map(|k| ((k as f64 + 0.5) * step) as usize).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn small_cases() {
        assert_eq!(evenly_spaced(5, 0), [0, 1, 2, 3, 4]);
        assert_eq!(evenly_spaced(5, 9), [0, 1, 2, 3, 4]);
        assert_eq!(evenly_spaced(10, 2), [2, 7]);
        assert_eq!(evenly_spaced(0, 3), Vec::<usize>::new());
    }

    proptest! {
        #[test]
        fn strictly_increasing_in_range_and_sized(len in 0usize..500, n in 0usize..600) {
            let v = evenly_spaced(len, n);
            prop_assert_eq!(v.len(), if n == 0 { len } else { n.min(len) });
            prop_assert!(v.windows(2).all(|w| w[0] < w[1]));
            prop_assert!(v.iter().all(|&i| i < len));
        }
    }
}
