//! Where a server-tick run's wall time goes, a few ticks at a time: the server's tick,
//! the bots' untimed work, the staleness and error probe, and the rest (waiting for the
//! receiver thread, and what of the tick no stage times). Logged as the run goes, so a run stopped by a time limit still
//! says which part made it long (the probe on a GPU host took minutes where the tick
//! took seconds, and nothing said so).

/// Sums of the last ticks' parts, in milliseconds.
#[derive(Debug)]
pub(super) struct Pace {
    every: u32,
    ticks: u32,
    wall: f64,
    server: f64,
    bots: f64,
    probe: f64,
}

impl Pace {
    /// A line every `every` ticks (at least 1).
    pub fn new(every: u32) -> Pace {
        Pace { every: every.max(1), ticks: 0, wall: 0.0, server: 0.0, bots: 0.0, probe: 0.0 }
    }

    /// One tick's parts (ms): its whole wall time, the server's tick, the bots' untimed
    /// work and the probe. Every `every` ticks, the line for them (`done` of `total`
    /// ticks run), and the sums start again.
    pub fn add(&mut self, done: u64, total: u64, wall: f64, server: f64, bots: f64, probe: f64) -> Option<String> {
        self.ticks += 1;
        self.wall += wall;
        self.server += server;
        self.bots += bots;
        self.probe += probe;
        if self.ticks < self.every {
            return None;
        }
        let n = f64::from(self.ticks);
        let other = (self.wall - self.server - self.bots - self.probe).max(0.0);
        let line = format!(
            "  ticks {done}/{total}: {:.1} ms a tick's wall = server {:.2} + bots {:.1} + probe {:.1} + the rest {:.1} \
             (means of the last {})",
            self.wall / n,
            self.server / n,
            self.bots / n,
            self.probe / n,
            other / n,
            self.ticks
        );
        *self = Pace::new(self.every);
        Some(line)
    }
}

#[cfg(test)]
mod tests {
    use super::Pace;

    #[test]
    fn a_line_every_few_ticks_with_the_means_of_those_ticks() {
        let mut pace = Pace::new(2);
        assert_eq!(pace.add(1, 4, 10.0, 1.0, 2.0, 3.0), None);
        let line = pace.add(2, 4, 30.0, 3.0, 4.0, 5.0).expect("a line after two ticks");
        assert_eq!(
            line,
            "  ticks 2/4: 20.0 ms a tick's wall = server 2.00 + bots 3.0 + probe 4.0 + the rest 11.0 (means of the last 2)"
        );
        // The sums started again: the next line is the next two ticks' alone.
        assert_eq!(pace.add(3, 4, 1.0, 1.0, 0.0, 0.0), None);
        let line = pace.add(4, 4, 3.0, 1.0, 0.0, 0.0).expect("a line after four ticks");
        assert!(
            line.starts_with("  ticks 4/4: 2.0 ms a tick's wall = server 1.00 + bots 0.0 + probe 0.0 + the rest 1.0"),
            "{line}"
        );
    }
}
