//! `torch.sort(stable=False)` on CPU sorts each row with libstdc++'s `std::sort` (introsort:
//! median-of-three quicksort down to 16-element runs, heapsort past the depth limit, then one
//! insertion sort), which is not stable. Reproducing it exactly makes equal depths (a coarse and
//! an importance sample at the same z) come out in the reference's order, so the merge
//! permutation matches the reference bit for bit.

/// Runs below this length are left to the final insertion sort (`_S_threshold`).
const THRESHOLD: usize = 16;

/// torch's ascending order: NaN after every number.
fn less(a: &(f32, u32), b: &(f32, u32)) -> bool {
    (!a.0.is_nan() && b.0.is_nan()) || a.0 < b.0
}

/// Sort (value, index) pairs ascending by value, ties as in torch.
pub fn sort(v: &mut [(f32, u32)]) {
    let n = v.len();
    if n >= 2 {
        sort_with_depth(v, 2 * (usize::BITS - 1 - n.leading_zeros()) as usize);
    }
}

/// `depth`: quicksort levels before falling back to heapsort (2·⌊log2 n⌋ in libstdc++).
pub(super) fn sort_with_depth(v: &mut [(f32, u32)], depth: usize) {
    let n = v.len();
    if n < 2 {
        return;
    }
    introsort_loop(v, 0, n, depth);
    if n > THRESHOLD {
        insertion_sort(v, 0, THRESHOLD);
        for i in THRESHOLD..n {
            unguarded_linear_insert(v, i);
        }
    } else {
        insertion_sort(v, 0, n);
    }
}

fn introsort_loop(v: &mut [(f32, u32)], first: usize, mut last: usize, mut depth: usize) {
    while last - first > THRESHOLD {
        if depth == 0 {
            heap_sort(&mut v[first..last]);
            return;
        }
        depth -= 1;
        let mid = first + (last - first) / 2;
        move_median_to_first(v, first, first + 1, mid, last - 1);
        let cut = unguarded_partition(v, first + 1, last, first);
        introsort_loop(v, cut, last, depth);
        last = cut;
    }
}

fn move_median_to_first(v: &mut [(f32, u32)], result: usize, a: usize, b: usize, c: usize) {
    let pick = if less(&v[a], &v[b]) {
        if less(&v[b], &v[c]) {
            b
        } else if less(&v[a], &v[c]) {
            c
        } else {
            a
        }
    } else if less(&v[a], &v[c]) {
        a
    } else if less(&v[b], &v[c]) {
        c
    } else {
        b
    };
    v.swap(result, pick);
}

fn unguarded_partition(
    v: &mut [(f32, u32)],
    mut first: usize,
    mut last: usize,
    pivot: usize,
) -> usize {
    loop {
        while less(&v[first], &v[pivot]) {
            first += 1;
        }
        last -= 1;
        while less(&v[pivot], &v[last]) {
            last -= 1;
        }
        if first >= last {
            return first;
        }
        v.swap(first, last);
        first += 1;
    }
}

fn insertion_sort(v: &mut [(f32, u32)], first: usize, last: usize) {
    for i in first + 1..last {
        if less(&v[i], &v[first]) {
            v[first..=i].rotate_right(1);
        } else {
            unguarded_linear_insert(v, i);
        }
    }
}

fn unguarded_linear_insert(v: &mut [(f32, u32)], mut last: usize) {
    let val = v[last];
    while less(&val, &v[last - 1]) {
        v[last] = v[last - 1];
        last -= 1;
    }
    v[last] = val;
}

/// `std::__partial_sort(first, last, last)`: make_heap then sort_heap.
fn heap_sort(v: &mut [(f32, u32)]) {
    let len = v.len();
    if len < 2 {
        return;
    }
    let mut parent = (len - 2) / 2;
    loop {
        let value = v[parent];
        adjust_heap(v, parent, len, value);
        if parent == 0 {
            break;
        }
        parent -= 1;
    }
    let mut last = len;
    while last > 1 {
        last -= 1;
        let value = v[last];
        v[last] = v[0];
        adjust_heap(&mut v[..last], 0, last, value);
    }
}

fn adjust_heap(v: &mut [(f32, u32)], mut hole: usize, len: usize, value: (f32, u32)) {
    let top = hole;
    let mut child = hole;
    while child < (len - 1) / 2 {
        child = 2 * (child + 1);
        if less(&v[child], &v[child - 1]) {
            child -= 1;
        }
        v[hole] = v[child];
        hole = child;
    }
    if len % 2 == 0 && child == (len - 2) / 2 {
        child = 2 * (child + 1);
        v[hole] = v[child - 1];
        hole = child - 1;
    }
    // push_heap
    let mut parent = hole.wrapping_sub(1) / 2;
    while hole > top && less(&v[parent], &value) {
        v[hole] = v[parent];
        hole = parent;
        parent = hole.wrapping_sub(1) / 2;
    }
    v[hole] = value;
}
