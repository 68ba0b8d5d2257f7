//! Reporting: the rows as Markdown tables beside the reference's, JSON lines, or CSV.

use std::fmt::Write as _;

use anyhow::Result;
use myriad_server::ServerConfig;

use super::{BenchArgs, Row};
use crate::reference;

fn fmt_ms(v: f64) -> String {
    if v >= 100.0 {
        format!("{v:.0}")
    } else if v >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

/// Markdown: our Table 1 and Table 2, then the reference's.
pub fn markdown(rows: &[Row], args: &BenchArgs) -> String {
    let mut s = String::new();
    let threads = rows.first().map_or(0, |r| r.threads);
    let _ = writeln!(
        s,
        "#### Table 1: physics time per tick (ms, median of {} ticks after {} warm-up; mean: their mean)\n",
        args.ticks, args.warmup
    );
    let _ = writeln!(
        s,
        "| scenario | backend | static | dynamic | total | mean | CPU per tick | dynamic pairs | static pairs | state hash |"
    );
    let _ = writeln!(s, "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |");
    for r in rows.iter().filter(|r| !r.is_server()) {
        match &r.skipped {
            Some(why) => {
                let _ = writeln!(s, "| {} | {} | - | - | - | - | | | | {why} |", r.scenario, r.backend);
            }
            None => {
                let _ = writeln!(
                    s,
                    "| {} | {} | {} | {} | {} | {} | {} | {} | {} | `{}` |",
                    r.scenario,
                    r.backend,
                    fmt_ms(r.physics_static_ms),
                    fmt_ms(r.physics_dynamic_ms),
                    fmt_ms(r.total_ms),
                    fmt_ms(r.mean_ms),
                    fmt_ms(r.cpu_ms),
                    r.dynamic_pairs,
                    r.static_pairs,
                    r.state_hash
                );
            }
        }
    }
    // Table 2 is the whole server tick where it was run; without it (--physics-only),
    // the physics rows with `packets` and `send` at 0.
    let server_rows: Vec<&Row> = rows.iter().filter(|r| r.is_server() && r.skipped.is_none()).collect();
    let table2: Vec<&Row> = if server_rows.is_empty() {
        rows.iter().filter(|r| r.skipped.is_none()).collect()
    } else {
        server_rows.clone()
    };
    let _ = writeln!(s, "\n#### Table 2: time per stage (ms, medians)\n");
    let _ = writeln!(s, "| scenario | backend | {} |", reference::STAGES.join(" | "));
    let _ = writeln!(s, "| --- | --- |{}", " ---: |".repeat(reference::STAGES.len()));
    for r in &table2 {
        let cells: Vec<String> = r.stages().iter().map(|&v| fmt_ms(v)).collect();
        let _ = writeln!(s, "| {} | {} | {} |", r.scenario, r.label(), cells.join(" | "));
    }
    if server_rows.is_empty() {
        let _ = writeln!(
            s,
            "\n`packets` and `send` belong to the server tick and are 0 in a physics-only run. cpu threads: {threads}."
        );
    } else {
        let _ = writeln!(s, "\n#### Table 3: the whole server tick (medians per tick; one bot per user on loopback)\n");
        let _ = writeln!(
            s,
            "| scenario | backend | AOI edge | players | tick | server CPU | receive | packets | of which AOI query | send | datagrams | KiB sent | kB/s per player | records | actions in | bots per socket | received by bots | lost | opened by bots | min. opening players seeing themselves |"
        );
        let _ = writeln!(s, "| --- | --- |{}", " ---: |".repeat(18));
        for r in &server_rows {
            let Some(t) = &r.server else { continue };
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {:.0} | {:.1} | {} | {} | {} | {} | {} | {} | {} of {} |",
                r.scenario,
                r.backend,
                t.aoi_size,
                t.players,
                fmt_ms(r.total_ms),
                fmt_ms(r.cpu_ms),
                fmt_ms(r.receive),
                fmt_ms(r.packets),
                fmt_ms(t.aoi_query),
                fmt_ms(r.send),
                t.datagrams,
                t.bytes as f64 / 1024.0,
                t.bytes_per_player_s / 1000.0,
                t.records,
                t.actions_received,
                t.bots_per_socket,
                t.delivered,
                t.lost,
                t.opened,
                t.min_saw_own,
                t.opening_bots
            );
        }
        let _ = writeln!(
            s,
            "\n`tick` is the sum of the stages (receive included); `server CPU` is the process's CPU time less the bots'. \
             `send` is the mean socket's time sending (the sockets send at once), `packets` the rest of building \
             and sending; `of which AOI query`: the backend's AOI query (on the device with `cuda`, the lists \
             copied back included). \
             `kB/s per player`: bytes sent per tick and player at the nominal tick rate ({} Hz). \
             Each bot sends an action every {} ticks. `received by bots`: datagrams that reached the bot whose \
             session their header names (`lost`: sent but received by none, over the whole run); `opened by bots`: \
             of those, the ones opened with the bot's key (tag, replay window, decode), all of them unless the run \
             had `--open-every N` (each bot then opens its own on every Nth tick, in turn: {}); the last column \
             counts the players that found their own object among those that opened on that tick. \
             cpu threads: {threads}.",
            ServerConfig::default().tick_rate,
            myriad_server::tick_bench::ACTION_EVERY,
            server_rows.iter().filter_map(|r| r.server.as_ref()).next().map_or_else(String::new, |t| {
                match t.open_every {
                    1 => "this run opened every datagram".to_string(),
                    n => format!("this run had --open-every {n}"),
                }
            })
        );
        quality_table(&mut s, &server_rows);
        shadow_table(&mut s, &server_rows);
    }
    let _ = writeln!(s, "\n#### The reference ({})\n", reference::MACHINE);
    let _ = writeln!(
        s,
        "| scenario | CPU static | CPU dynamic | naive GPU static | naive GPU dynamic | optimized GPU static | optimized GPU dynamic |"
    );
    let _ = writeln!(s, "| --- | ---: | ---: | ---: | ---: | ---: | ---: |");
    for (name, v) in reference::TABLE1 {
        let cells: Vec<String> = v.iter().map(|c| c.map_or("-".into(), |x| format!("{x}"))).collect();
        let _ = writeln!(s, "| {name} | {} |", cells.join(" | "));
    }
    let _ = writeln!(s, "\n| scenario (optimized GPU) | {} |", reference::STAGES.join(" | "));
    let _ = writeln!(s, "| --- |{}", " ---: |".repeat(reference::STAGES.len()));
    for (name, v) in reference::TABLE2 {
        let cells: Vec<String> = v.iter().map(|x| format!("{x}")).collect();
        let _ = writeln!(s, "| {name} | {} |", cells.join(" | "));
    }
    s
}

/// A second configuration of protocol 3 beside the live server, on the same sampled
/// players (`bench/shadow.rs`).
fn shadow_table(s: &mut String, rows: &[&Row]) {
    let with: Vec<(&Row, &super::ServerTick, &super::shadow::ShadowRow)> =
        rows.iter().filter_map(|r| r.server.as_ref().and_then(|t| t.shadow.as_ref().map(|q| (*r, t, q)))).collect();
    if with.is_empty() {
        return;
    }
    let _ = writeln!(s, "\n#### Another configuration of protocol 3 beside the live server, same players and ticks\n");
    let _ = writeln!(
        s,
        "| scenario | backend | AOI edge | protocol | budget kbit/s | near bound (ticks) | kB/s per player | information age ≤30 p50 / p99 / max (ms) | AOI p50 / p99 / max (ms) | error ≤30 p50 / p99 | error AOI p50 / p99 | missing ≤30 / AOI | relative records | unresolved |"
    );
    let _ = writeln!(s, "| --- | --- |{}", " ---: |".repeat(12));
    for (r, t, sh) in &with {
        for (name, q, kbs, budget, bound, relative) in [
            (
                "live".to_string(),
                &sh.live,
                t.bytes_per_player_s / 1000.0,
                "-".to_string(),
                "-".to_string(),
                "-".to_string(),
            ),
            (
                if sh.link == super::shadow::Link::default() {
                    "shadow".to_string()
                } else {
                    format!(
                        "shadow, {:.0} % loss, {:.0} ± {:.0} ms",
                        sh.link.loss * 100.0,
                        sh.link.delay_ms,
                        sh.link.jitter_ms
                    )
                },
                &sh.v2,
                sh.bytes_per_player_s / 1000.0,
                format!("{:.0}", sh.budget_kbps),
                format!("{}", sh.near_bound_ticks),
                format!("{:.0} %", sh.relative_share * 100.0),
            ),
        ] {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {name} | {budget} | {bound} | {kbs:.1} | {} | {relative} | {} |",
                r.scenario,
                r.backend,
                t.aoi_size,
                figure_cells(q),
                sh.unresolved,
            );
        }
    }
    let _ = writeln!(
        s,
        "\nInformation age: 0 when the state a client holds is the object's current quantized position, else the \
         age of that state (protocol 3 sends an unchanged object only to confirm it now and then). The live row's \
         kB/s is over all players, the shadow's over the sampled ones (acknowledged before the next tick unless \
         its simulated link delays or loses them)."
    );
}

/// The staleness, error and missing cells of one row of the quality and shadow tables.
fn figure_cells(q: &super::QualityRowFigures) -> String {
    let (sn, sa, en, ea) = (&q.staleness_near_ms, &q.staleness_all_ms, &q.error_near, &q.error_all);
    format!(
        "{:.0} / {:.0} / {:.0} | {:.0} / {:.0} / {:.0} | {:.3} / {:.3} | {:.3} / {:.3} | {} / {}",
        sn.p50, sn.p99, sn.max, sa.p50, sa.p99, sa.max, en.p50, en.p99, ea.p50, ea.p99, q.missing_near, q.missing_all
    )
}

/// Table 3's second part: what the sampled players' clients held and drew.
fn quality_table(s: &mut String, rows: &[&Row]) {
    let with: Vec<(&Row, &super::ServerTick, &super::QualityRow)> =
        rows.iter().filter_map(|r| r.server.as_ref().and_then(|t| t.quality.as_ref().map(|q| (*r, t, q)))).collect();
    let Some((_, _, first)) = with.first() else { return };
    let _ = writeln!(
        s,
        "\n#### Table 3, continued: what a player gets ({} sampled players a run, every {} ticks, render delay {} ticks)\n",
        first.players, first.every, first.render_delay_ticks
    );
    let _ = writeln!(
        s,
        "| scenario | backend | AOI edge | kB/s per player | staleness ≤30 p50 / p99 / max (ms) | staleness AOI p50 / p99 / max (ms) | error ≤30 p50 / p99 | error AOI p50 / p99 | missing ≤30 / AOI | information age ≤30 p50 / p99 / max (ms) | information age AOI p50 / p99 / max (ms) |"
    );
    let _ = writeln!(s, "| --- | --- |{}", " ---: |".repeat(9));
    for (r, t, q) in &with {
        let (inear, iall) = (&q.information.staleness_near_ms, &q.information.staleness_all_ms);
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.1} | {} | {:.0} / {:.0} / {:.0} | {:.0} / {:.0} / {:.0} |",
            r.scenario,
            r.backend,
            t.aoi_size,
            t.bytes_per_player_s / 1000.0,
            figure_cells(&q.figures),
            inear.p50,
            inear.p99,
            inear.max,
            iall.p50,
            iall.p99,
            iall.max,
        );
    }
    let _ = writeln!(
        s,
        "\nStaleness: the age of the newest state a sampled client holds of each object whose centre is in its \
         AOI cube (its own object left out), on the server's clock right after the tick's updates arrived (loopback: \
         no network delay); ≤30: objects within 30 units. Error: the distance (units) between the client's \
         position of the object at render tick T (interpolated with the render delay, extrapolated at most \
         the cap, then held) and the server's true position at T. Missing: objects in the AOI of which the client \
         held no state when sampled (not in the staleness or error percentiles). Information age: 0 while the \
         state the client holds is the object's current quantized position, else the time since the object moved \
         away from it (protocol 3 sends an unchanged object only to confirm it now and then, so its newest state \
         can be old and still current)."
    );
}

/// One JSON object per line.
pub fn json(rows: &[Row]) -> Result<String> {
    let mut s = String::new();
    for r in rows {
        s.push_str(&serde_json::to_string(r)?);
        s.push('\n');
    }
    Ok(s)
}

/// CSV with a header line: one column per field, nested fields as `server.players`
/// and so on, empty where a row does not have the field (physics rows have no
/// `server.*`).
pub fn csv(rows: &[Row]) -> Result<String> {
    fn flatten(prefix: &str, v: &serde_json::Value, out: &mut Vec<(String, String)>) {
        match v {
            serde_json::Value::Object(o) => {
                for (k, v) in o {
                    let key = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                    flatten(&key, v, out);
                }
            }
            serde_json::Value::String(t) => out.push((prefix.into(), format!("\"{}\"", t.replace('"', "\"\"")))),
            serde_json::Value::Null => out.push((prefix.into(), String::new())),
            other => out.push((prefix.into(), other.to_string())),
        }
    }
    let mut flat = Vec::with_capacity(rows.len());
    let mut header: Vec<String> = Vec::new();
    for r in rows {
        let mut cells = Vec::new();
        flatten("", &serde_json::to_value(r)?, &mut cells);
        for (k, _) in &cells {
            if !header.contains(k) {
                header.push(k.clone());
            }
        }
        flat.push(cells);
    }
    let mut s = header.join(",");
    s.push('\n');
    for cells in &flat {
        let line: Vec<&str> =
            header.iter().map(|h| cells.iter().find(|(k, _)| k == h).map_or("", |(_, v)| v.as_str())).collect();
        s.push_str(&line.join(","));
        s.push('\n');
    }
    Ok(s)
}
