//! Server metrics in the Prometheus text exposition format (version 0.0.4), kept in atomics so
//! recording never blocks a request: requests by outcome, refusals by reason, a latency
//! histogram of `POST /v1/localize`, and the in-flight and queued gauges.

use std::fmt::Write;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::time::Duration;

/// How a `POST /v1/localize` request ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// A pose was returned.
    Localized,
    /// The localizer ran and refused (confidence below the calibrated threshold).
    Refused,
    /// The best place hypothesis is in a block this process does not serve.
    OutsideBlocks,
    /// Malformed request (4xx other than 413).
    BadRequest,
    /// The body was larger than the limit (413).
    PayloadTooLarge,
    /// Workers and queue were full (503).
    Overloaded,
    /// The request ran past the timeout (504).
    Timeout,
    /// The server is shutting down (503).
    ShuttingDown,
    /// The localizer failed (500).
    Error,
}

impl Outcome {
    /// Every outcome, in the order the metrics list them.
    pub const ALL: [Outcome; 9] = [
        Outcome::Localized,
        Outcome::Refused,
        Outcome::OutsideBlocks,
        Outcome::BadRequest,
        Outcome::PayloadTooLarge,
        Outcome::Overloaded,
        Outcome::Timeout,
        Outcome::ShuttingDown,
        Outcome::Error,
    ];

    /// Label value (and the `status` of a response body).
    pub fn name(self) -> &'static str {
        match self {
            Outcome::Localized => "localized",
            Outcome::Refused => "refused",
            Outcome::OutsideBlocks => "outside_blocks",
            Outcome::BadRequest => "bad_request",
            Outcome::PayloadTooLarge => "payload_too_large",
            Outcome::Overloaded => "overloaded",
            Outcome::Timeout => "timeout",
            Outcome::ShuttingDown => "shutting_down",
            Outcome::Error => "error",
        }
    }

    fn index(self) -> usize {
        Outcome::ALL.iter().position(|&o| o == self).unwrap_or(0)
    }
}

/// Upper bounds of the latency histogram's buckets, seconds.
pub const LATENCY_BUCKETS_S: [f64; 14] = [
    0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0,
];

/// The server's counters and gauges.
#[derive(Debug, Default)]
pub struct Metrics {
    requests: [AtomicU64; Outcome::ALL.len()],
    /// Per bucket of [`LATENCY_BUCKETS_S`] (not cumulative), then the overflow.
    buckets: [AtomicU64; LATENCY_BUCKETS_S.len() + 1],
    latency_sum_us: AtomicU64,
    in_flight: AtomicI64,
    queued: AtomicI64,
}

/// Keeps a gauge raised while it lives.
pub struct GaugeGuard<'a>(&'a AtomicI64);

impl Drop for GaugeGuard<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

impl Metrics {
    /// Records a finished request.
    pub fn observe(&self, outcome: Outcome, elapsed: Duration) {
        self.requests[outcome.index()].fetch_add(1, Ordering::Relaxed);
        let s = elapsed.as_secs_f64();
        let b = LATENCY_BUCKETS_S
            .iter()
            .position(|&ub| s <= ub)
            .unwrap_or(LATENCY_BUCKETS_S.len());
        self.buckets[b].fetch_add(1, Ordering::Relaxed);
        self.latency_sum_us
            .fetch_add(elapsed.as_micros() as u64, Ordering::Relaxed);
    }

    /// Requests that ended with `outcome` so far.
    pub fn count(&self, outcome: Outcome) -> u64 {
        self.requests[outcome.index()].load(Ordering::Relaxed)
    }

    /// Raises the in-flight gauge (queries on a worker) until the guard drops.
    pub fn in_flight(&self) -> GaugeGuard<'_> {
        self.in_flight.fetch_add(1, Ordering::Relaxed);
        GaugeGuard(&self.in_flight)
    }

    /// Raises the queue gauge (admitted, not yet on a worker) until the guard drops.
    pub fn queued(&self) -> GaugeGuard<'_> {
        self.queued.fetch_add(1, Ordering::Relaxed);
        GaugeGuard(&self.queued)
    }

    /// Current (in flight, queued).
    pub fn gauges(&self) -> (i64, i64) {
        (
            self.in_flight.load(Ordering::Relaxed),
            self.queued.load(Ordering::Relaxed),
        )
    }

    /// The metrics as Prometheus text; `workers` and `queue` are the configured capacities.
    pub fn render(&self, workers: usize, queue: usize) -> String {
        let mut s = String::new();
        let _ = self.write(&mut s, workers, queue);
        s
    }

    fn write(&self, s: &mut String, workers: usize, queue: usize) -> std::fmt::Result {
        writeln!(
            s,
            "# HELP matloc_serve_requests_total Localization requests by outcome."
        )?;
        writeln!(s, "# TYPE matloc_serve_requests_total counter")?;
        for o in Outcome::ALL {
            writeln!(
                s,
                "matloc_serve_requests_total{{outcome=\"{}\"}} {}",
                o.name(),
                self.count(o)
            )?;
        }
        writeln!(
            s,
            "# HELP matloc_serve_refusals_total Queries answered without a pose, by reason."
        )?;
        writeln!(s, "# TYPE matloc_serve_refusals_total counter")?;
        writeln!(
            s,
            "matloc_serve_refusals_total{{reason=\"low_confidence\"}} {}",
            self.count(Outcome::Refused)
        )?;
        writeln!(
            s,
            "matloc_serve_refusals_total{{reason=\"outside_blocks\"}} {}",
            self.count(Outcome::OutsideBlocks)
        )?;
        writeln!(
            s,
            "# HELP matloc_serve_request_duration_seconds Time from arrival to response of POST /v1/localize."
        )?;
        writeln!(s, "# TYPE matloc_serve_request_duration_seconds histogram")?;
        let mut cumulative = 0;
        for (i, ub) in LATENCY_BUCKETS_S.iter().enumerate() {
            cumulative += self.buckets[i].load(Ordering::Relaxed);
            writeln!(
                s,
                "matloc_serve_request_duration_seconds_bucket{{le=\"{ub}\"}} {cumulative}"
            )?;
        }
        cumulative += self.buckets[LATENCY_BUCKETS_S.len()].load(Ordering::Relaxed);
        writeln!(
            s,
            "matloc_serve_request_duration_seconds_bucket{{le=\"+Inf\"}} {cumulative}"
        )?;
        writeln!(
            s,
            "matloc_serve_request_duration_seconds_sum {}",
            self.latency_sum_us.load(Ordering::Relaxed) as f64 / 1e6
        )?;
        writeln!(
            s,
            "matloc_serve_request_duration_seconds_count {cumulative}"
        )?;
        let (in_flight, queued) = self.gauges();
        for (name, help, value) in [
            (
                "matloc_serve_in_flight",
                "Queries running on a worker.",
                in_flight,
            ),
            (
                "matloc_serve_queue_depth",
                "Queries admitted and waiting (body upload or a free worker).",
                queued,
            ),
            (
                "matloc_serve_workers",
                "Configured workers.",
                workers as i64,
            ),
            (
                "matloc_serve_queue_capacity",
                "Configured queue length beyond the workers.",
                queue as i64,
            ),
        ] {
            writeln!(s, "# HELP {name} {help}")?;
            writeln!(s, "# TYPE {name} gauge")?;
            writeln!(s, "{name} {value}")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_is_cumulative_and_counts_match() {
        let m = Metrics::default();
        m.observe(Outcome::Localized, Duration::from_millis(3));
        m.observe(Outcome::Localized, Duration::from_millis(300));
        m.observe(Outcome::Overloaded, Duration::from_secs(500));
        let _g = m.in_flight();
        let text = m.render(2, 4);
        assert!(text.contains("matloc_serve_requests_total{outcome=\"localized\"} 2"));
        assert!(text.contains("matloc_serve_request_duration_seconds_bucket{le=\"0.005\"} 1"));
        assert!(text.contains("matloc_serve_request_duration_seconds_bucket{le=\"0.5\"} 2"));
        assert!(text.contains("matloc_serve_request_duration_seconds_bucket{le=\"+Inf\"} 3"));
        assert!(text.contains("matloc_serve_request_duration_seconds_count 3"));
        assert!(text.contains("matloc_serve_in_flight 1"));
        assert!(text.contains("matloc_serve_workers 2"));
    }
}
