//! PNG charts for the command reports, drawn with plotters on an in-memory bitmap: error CDFs,
//! top-down maps, stage-time bars and the partition map. The functions take plain data (world
//! coordinates in metres, names, colours by palette index); text uses an embedded DejaVu Sans, so
//! no system font is needed. Non-finite values are skipped, geometry outside the view is clipped.

use std::path::Path;
use std::sync::OnceLock;

use anyhow::{Context, Result, anyhow, bail};
use image::ImageEncoder;
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::{FontStyle, register_font};

/// Font family name every chart's text uses.
const FONT: &str = "sans-serif";
/// DejaVu Sans 2.37 (Bitstream Vera licence: `assets/DejaVuSans-LICENSE.txt`).
static FONT_TTF: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// Text colour.
const INK: RGBColor = RGBColor(25, 25, 25);
/// Colour of cameras and points that belong to no group.
const GREY: RGBColor = RGBColor(140, 140, 140);
// Text sizes in pixels. Even sizes keep every glyph on the same baseline: the ab_glyph text
// path rounds half the size together with each glyph's top.
/// Title text size.
const TITLE_PX: u32 = 22;
/// Axis-description text size.
const DESC_PX: u32 = 16;
/// Tick-label text size.
const LABEL_PX: u32 = 14;
/// Legend text size.
const LEGEND_PX: u32 = 14;

type Area<'a> = DrawingArea<BitMapBackend<'a>, Shift>;

/// A categorical colour for index `i` (twelve distinct hues, then repeating; no grey, which
/// marks "no group").
pub fn palette(i: usize) -> RGBColor {
    const P: [RGBColor; 12] = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
        RGBColor(214, 39, 40),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(227, 119, 194),
        RGBColor(188, 189, 34),
        RGBColor(23, 190, 207),
        RGBColor(0, 0, 128),
        RGBColor(128, 128, 0),
        RGBColor(140, 0, 70),
    ];
    P[i % P.len()]
}

/// One method's localization errors for [`error_cdfs`].
pub struct ErrorSeries<'a> {
    /// Legend name.
    pub name: &'a str,
    /// Translation errors of the returned poses, metres.
    pub translation_m: &'a [f64],
    /// Rotation errors of the returned poses, degrees.
    pub rotation_deg: &'a [f64],
    /// Queries attempted, refused ones included: each curve ends at returned / attempted.
    pub queries: usize,
}

/// Writes the cumulative error distributions: translation (log metres) and rotation (log
/// degrees) side by side, one line per series, colour `palette(index)`.
pub fn error_cdfs(path: &Path, title: &str, series: &[ErrorSeries<'_>]) -> Result<()> {
    let (w, h) = (1400u32, 620u32);
    let entries: Vec<(Mark, String)> = series
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let returned = s.translation_m.iter().filter(|v| v.is_finite()).count();
            let queries = s.queries.max(returned);
            let mark = Mark::Line(palette(i));
            (mark, format!("{} ({returned}/{queries} returned)", s.name))
        })
        .collect();
    let rows = legend_rows(&entries, w - 40)?;
    let legend_h = 8 + 24 * rows.len() as u32;
    render(path, (w, h), |root| {
        let body = root.titled(title, text(TITLE_PX))?;
        let (legend, panels) = body.split_vertically(legend_h);
        draw_legend_rows(&legend, 20, 4, &rows)?;
        let (left, right) = panels.split_horizontally(w / 2);
        let translation: Vec<(&[f64], usize)> = series
            .iter()
            .map(|s| (s.translation_m, s.queries))
            .collect();
        cdf_panel(
            &left,
            "translation error",
            "translation error (m, log scale)",
            (0.01, 100.0),
            &|v| {
                if *v < 0.95 {
                    format!("{:.0} cm", v * 100.0)
                } else {
                    format!("{v:.0} m")
                }
            },
            &translation,
        )?;
        let rotation: Vec<(&[f64], usize)> =
            series.iter().map(|s| (s.rotation_deg, s.queries)).collect();
        cdf_panel(
            &right,
            "rotation error",
            "rotation error (°, log scale)",
            (0.01, 180.0),
            &|v| {
                if *v < 0.95 {
                    format!("{}°", trim_float(*v))
                } else {
                    format!("{v:.0}°")
                }
            },
            &rotation,
        )?;
        Ok(())
    })
}

/// One log-x CDF panel over `range` with ticks at the powers of ten inside it.
fn cdf_panel(
    area: &Area<'_>,
    caption: &str,
    x_desc: &str,
    range: (f64, f64),
    x_label: &dyn Fn(&f64) -> String,
    data: &[(&[f64], usize)],
) -> Result<()> {
    let (lo, hi) = range;
    let mut major = Vec::new();
    let mut minor = Vec::new();
    let mut decade = 10f64.powf(lo.log10().floor());
    while decade <= hi * 1.0001 {
        if decade >= lo * 0.9999 {
            major.push(decade);
        }
        for m in 2..10 {
            let v = decade * f64::from(m);
            if v > lo && v < hi {
                minor.push(v);
            }
        }
        decade *= 10.0;
    }
    let y_top = 1.03;
    let mut chart = ChartBuilder::on(area)
        .margin(12)
        .margin_right(30)
        .caption(caption, text(DESC_PX + 2))
        .x_label_area_size(58)
        .y_label_area_size(78)
        .build_cartesian_2d(
            (lo..hi)
                .log_scale()
                .with_key_points(major)
                .with_light_points(minor),
            0.0..y_top,
        )?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc("queries within error (%)")
        .y_labels(6)
        .axis_desc_style(text(DESC_PX))
        .label_style(text(LABEL_PX))
        .x_label_formatter(x_label)
        .y_label_formatter(&|v| format!("{:.0} %", v * 100.0))
        .bold_line_style(RGBColor(200, 200, 200))
        .light_line_style(RGBColor(236, 236, 236))
        .axis_style(INK)
        .draw()?;
    for (i, (values, queries)) in data.iter().enumerate() {
        let mut v: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
        v.sort_by(f64::total_cmp);
        let n = (*queries).max(v.len()).max(1) as f64;
        let mut pts = vec![(lo, 0.0)];
        for (k, &e) in v.iter().enumerate() {
            let x = e.clamp(lo, hi);
            pts.push((x, k as f64 / n));
            pts.push((x, (k + 1) as f64 / n));
        }
        pts.push((hi, v.len() as f64 / n));
        chart.draw_series(LineSeries::new(pts, palette(i).stroke_width(2)))?;
    }
    Ok(())
}

/// An axis-aligned box seen from above, drawn as an outline with its label in the top-left corner.
pub struct MapBox {
    /// Lower corner (x, y), metres.
    pub min: [f64; 2],
    /// Upper corner (x, y), metres.
    pub max: [f64; 2],
    /// Palette index of the outline.
    pub color: usize,
    /// Text written inside the top-left corner.
    pub label: String,
}

/// One method's position estimates, each joined to its ground truth by a line.
pub struct EstimateSeries<'a> {
    /// Legend name.
    pub name: &'a str,
    /// (ground truth, estimate) position pairs, metres.
    pub pairs: &'a [([f64; 2], [f64; 2])],
}

/// Contents of a [`topdown`] map.
pub struct TopDown<'a> {
    /// Title above the map.
    pub title: &'a str,
    /// Training camera positions (small grey dots).
    pub train_cameras: &'a [[f64; 2]],
    /// Boxes such as sub-NeRF block bounds.
    pub boxes: &'a [MapBox],
    /// Legend text for the boxes.
    pub boxes_legend: &'a str,
    /// Ground-truth query positions (black rings).
    pub truth: &'a [[f64; 2]],
    /// Estimates per method, colour `palette(index)`.
    pub estimates: &'a [EstimateSeries<'a>],
}

/// Writes a top-down map (x right, y up, equal scale) with a legend on the right. The view
/// covers the training cameras, boxes and truth; estimates outside it are clipped at its border.
pub fn topdown(path: &Path, map: &TopDown<'_>) -> Result<()> {
    let (w, h) = (1200u32, 900u32);
    let legend_w = 290;
    let extent = Extent::of(
        map.train_cameras
            .iter()
            .chain(map.truth)
            .chain(map.boxes.iter().flat_map(|b| [&b.min, &b.max])),
    );
    render(path, (w, h), |root| {
        let body = root.titled(map.title, text(TITLE_PX))?;
        let (plot_area, legend) = body.split_horizontally(w - legend_w);
        let mut chart = equal_aspect_chart(&plot_area, extent)?;
        let (min, max) = view_of(&chart);
        for b in map.boxes {
            if !(finite(b.min) && finite(b.max)) {
                continue;
            }
            let col = palette(b.color);
            let (lo, hi) = (clamp_to(b.min, min, max), clamp_to(b.max, min, max));
            chart.draw_series([Rectangle::new(
                [(lo[0], lo[1]), (hi[0], hi[1])],
                col.stroke_width(2),
            )])?;
            if inside([b.min[0], b.max[1]], min, max) {
                chart.draw_series([EmptyElement::at((b.min[0], b.max[1]))
                    + Text::new(b.label.clone(), (5, 4), text(12).color(&col))])?;
            }
        }
        let dots = |pts: &[[f64; 2]], r: u32, col: RGBAColor| {
            pts.iter()
                .filter(|p| inside(**p, min, max))
                .map(move |p| Circle::new((p[0], p[1]), r, col.filled()))
                .collect::<Vec<_>>()
        };
        chart.draw_series(dots(map.train_cameras, 2, GREY.mix(0.7)))?;
        for (i, s) in map.estimates.iter().enumerate() {
            let col = palette(i);
            let lines = s.pairs.iter().filter_map(|(g, e)| {
                let (a, b) = clip_segment(*g, *e, min, max)?;
                Some(PathElement::new(
                    vec![(a[0], a[1]), (b[0], b[1])],
                    col.stroke_width(1),
                ))
            });
            chart.draw_series(lines)?;
            let ests: Vec<[f64; 2]> = s.pairs.iter().map(|p| p.1).collect();
            chart.draw_series(dots(&ests, 4, col.mix(0.85)))?;
        }
        // Rings, so that estimates right on the truth stay visible.
        chart.draw_series(
            map.truth
                .iter()
                .filter(|p| inside(**p, min, max))
                .map(|p| Circle::new((p[0], p[1]), 5, INK.stroke_width(2))),
        )?;

        let mut entries = vec![
            (Mark::Dot(GREY, 3), "training camera".to_string()),
            (Mark::Circle(INK), "query ground truth".to_string()),
        ];
        if !map.boxes.is_empty() {
            entries.push((
                Mark::Outline(palette(map.boxes[0].color)),
                map.boxes_legend.to_string(),
            ));
        }
        for (i, s) in map.estimates.iter().enumerate() {
            entries.push((Mark::DotLine(palette(i)), format!("{} estimate", s.name)));
        }
        let mut y = 24;
        for (mark, label) in &entries {
            draw_entry(&legend, 10, y, mark, label)?;
            y += 26;
        }
        y += 10;
        for line in ["lines join each estimate", "to its ground truth"] {
            legend_text(&legend, 10, y, line, 14)?;
            y += 20;
        }
        Ok(())
    })
}

/// One horizontal stacked bar of [`stage_bars`].
pub struct StackedBar<'a> {
    /// Label left of the bar.
    pub label: &'a str,
    /// (part name, value) in drawing order; a part's colour follows its name.
    pub parts: &'a [(String, f64)],
}

/// Width of a [`stage_bars`] chart, pixels.
const BARS_W: u32 = 1100;

/// Height of a [`stage_bars`] chart with `bars` bars and `legend_rows` legend rows, pixels.
fn bars_height(bars: usize, legend_rows: usize) -> u32 {
    160 + 56 * bars.max(1) as u32 + 24 * legend_rows as u32
}

/// Writes horizontal stacked bars, first entry on top, each with its total and `unit` after it,
/// and a legend of the part names below.
pub fn stage_bars(
    path: &Path,
    title: &str,
    x_desc: &str,
    unit: &str,
    bars: &[StackedBar<'_>],
) -> Result<()> {
    let mut names: Vec<&str> = Vec::new();
    for b in bars {
        for (s, _) in b.parts {
            if !names.contains(&s.as_str()) {
                names.push(s);
            }
        }
    }
    let value = |v: f64| {
        if v.is_finite() {
            v.clamp(0.0, 1e12)
        } else {
            0.0
        }
    };
    let totals: Vec<f64> = bars
        .iter()
        .map(|b| b.parts.iter().map(|p| value(p.1)).sum())
        .collect();
    let max_total = totals.iter().copied().fold(0.0, f64::max);
    let x_max = if max_total > 0.0 {
        max_total * 1.18
    } else {
        1.0
    };
    let w = BARS_W;
    let entries: Vec<(Mark, String)> = names
        .iter()
        .enumerate()
        .map(|(k, n)| (Mark::Fill(palette(k)), n.to_string()))
        .collect();
    let rows = legend_rows(&entries, w - 40)?;
    let legend_h = 10 + 24 * rows.len() as u32;
    let n = bars.len().max(1);
    let h = bars_height(bars.len(), rows.len());
    let label_w = bars
        .iter()
        .map(|b| text_width(b.label, LABEL_PX))
        .collect::<Result<Vec<_>>>()?
        .into_iter()
        .max()
        .unwrap_or(0)
        + 20;
    render(path, (w, h), |root| {
        let body = root.titled(title, text(TITLE_PX))?;
        let (chart_area, legend) =
            body.split_vertically(body.dim_in_pixel().1.saturating_sub(legend_h));
        let mut chart = ChartBuilder::on(&chart_area)
            .margin(12)
            .margin_right(30)
            .x_label_area_size(55)
            .y_label_area_size(label_w.clamp(60, w / 3))
            .build_cartesian_2d(0.0..x_max, 0.0..n as f64)?;
        chart
            .configure_mesh()
            .disable_y_mesh()
            .y_labels(0)
            .x_desc(x_desc)
            .axis_desc_style(text(DESC_PX))
            .label_style(text(LABEL_PX))
            .x_label_formatter(&|v| trim_float(*v))
            .bold_line_style(RGBColor(210, 210, 210))
            .light_line_style(RGBColor(240, 240, 240))
            .axis_style(INK)
            .draw()?;
        let right = Pos::new(HPos::Right, VPos::Center);
        let left = Pos::new(HPos::Left, VPos::Center);
        for (i, b) in bars.iter().enumerate() {
            // Bar 0 on top.
            let y0 = (n - 1 - i) as f64 + 0.18;
            let (y1, yc) = (y0 + 0.64, y0 + 0.32);
            chart.draw_series([EmptyElement::at((0.0, yc))
                + Text::new(b.label.to_string(), (-10, 0), text(LABEL_PX).pos(right))])?;
            let mut x = 0.0;
            for (s, t) in b.parts {
                let k = names.iter().position(|n| n == s).unwrap_or(0);
                let x1 = x + value(*t);
                if x1 > x {
                    chart
                        .draw_series([Rectangle::new([(x, y0), (x1, y1)], palette(k).filled())])?;
                }
                x = x1;
            }
            let total = format!("{} {unit}", significant(totals[i]));
            chart.draw_series([
                EmptyElement::at((x, yc)) + Text::new(total, (8, 0), text(LABEL_PX).pos(left))
            ])?;
        }
        draw_legend_rows(&legend, 20, 4, &rows)?;
        Ok(())
    })
}

/// A sub-NeRF block of a [`PartitionMap`].
pub struct PartitionBlock {
    /// Block id; its colour is `palette(id)`.
    pub id: usize,
    /// Lower corner (x, y) of the block box, metres.
    pub min: [f64; 2],
    /// Upper corner (x, y) of the block box, metres.
    pub max: [f64; 2],
    /// Training poses in the block.
    pub poses: usize,
    /// Sampling volume of the block box, cubic metres.
    pub volume_m3: f64,
}

/// A camera of a [`PartitionMap`].
pub struct CameraMark {
    /// Position (x, y), metres.
    pub position: [f64; 2],
    /// Viewing direction projected on the ground plane (unit length for a horizontal view).
    pub direction: [f64; 2],
    /// Block whose colour the camera gets (grey when none).
    pub block: Option<usize>,
    /// A test camera (drawn with a black ring) rather than a training one.
    pub test: bool,
}

/// Contents of a [`partition_map`].
pub struct PartitionMap<'a> {
    /// Title above the map.
    pub title: &'a str,
    /// Lower corner (x, y) of the scene, metres.
    pub scene_min: [f64; 2],
    /// Upper corner (x, y) of the scene, metres.
    pub scene_max: [f64; 2],
    /// Sample points and the block whose colour each gets.
    pub points: &'a [([f64; 2], usize)],
    /// Block boxes.
    pub blocks: &'a [PartitionBlock],
    /// Training and test cameras.
    pub cameras: &'a [CameraMark],
}

/// Writes the partition top-down map: sample points and block boxes coloured per block, cameras
/// with their viewing direction, and a legend with a per-block table on the right.
pub fn partition_map(path: &Path, map: &PartitionMap<'_>) -> Result<()> {
    let (w, h) = (1250u32, 900u32);
    let legend_w = 330;
    let extent = Extent::of(
        [&map.scene_min, &map.scene_max]
            .into_iter()
            .chain(map.cameras.iter().map(|c| &c.position)),
    );
    render(path, (w, h), |root| {
        let body = root.titled(map.title, text(TITLE_PX - 2))?;
        let (plot_area, legend) = body.split_horizontally(w - legend_w);
        let mut chart = equal_aspect_chart(&plot_area, extent)?;
        let (min, max) = view_of(&chart);
        chart.draw_series(
            map.points
                .iter()
                .filter(|(p, _)| inside(*p, min, max))
                .map(|(p, b)| Pixel::new((p[0], p[1]), palette(*b).mix(0.3))),
        )?;
        for b in map.blocks {
            if !(finite(b.min) && finite(b.max)) {
                continue;
            }
            let (lo, hi) = (clamp_to(b.min, min, max), clamp_to(b.max, min, max));
            chart.draw_series([Rectangle::new(
                [(lo[0], lo[1]), (hi[0], hi[1])],
                palette(b.id).stroke_width(2),
            )])?;
        }
        let ext = (max[0] - min[0]).max(max[1] - min[1]);
        let arrow = 0.035 * ext;
        for test in [false, true] {
            for c in map.cameras.iter().filter(|c| c.test == test) {
                let p = c.position;
                if !inside(p, min, max) {
                    continue;
                }
                let col = c.block.map_or(GREY, palette);
                let tip = [p[0] + c.direction[0] * arrow, p[1] + c.direction[1] * arrow];
                if let Some((a, b)) = clip_segment(p, tip, min, max) {
                    chart.draw_series([PathElement::new(
                        vec![(a[0], a[1]), (b[0], b[1])],
                        INK.stroke_width(1),
                    )])?;
                }
                if test {
                    chart.draw_series([Circle::new((p[0], p[1]), 6, INK.filled())])?;
                    chart.draw_series([Circle::new((p[0], p[1]), 4, col.filled())])?;
                } else {
                    // A white edge keeps the camera visible on its own block's points.
                    chart.draw_series([Circle::new((p[0], p[1]), 5, WHITE.filled())])?;
                    chart.draw_series([Circle::new((p[0], p[1]), 4, col.filled())])?;
                }
            }
        }

        // Legend: the block table, then the marks.
        let x = 10;
        let mut y = 14;
        let cols = [
            (x + 22, "block", HPos::Left),
            (x + 150, "poses", HPos::Right),
        ];
        for (cx, head, hpos) in cols {
            legend_text_at(&legend, cx, y, head, LEGEND_PX, hpos)?;
        }
        legend_text_at(&legend, x + 290, y, "box volume", LEGEND_PX, HPos::Right)?;
        y += 24;
        let shown = 24;
        for b in map.blocks.iter().take(shown) {
            legend.draw(&Rectangle::new(
                [(x, y - 6), (x + 14, y + 6)],
                palette(b.id).filled(),
            ))?;
            legend_text_at(&legend, x + 22, y, &b.id.to_string(), LEGEND_PX, HPos::Left)?;
            legend_text_at(
                &legend,
                x + 150,
                y,
                &b.poses.to_string(),
                LEGEND_PX,
                HPos::Right,
            )?;
            let vol = format!("{} m³", sci(b.volume_m3));
            legend_text_at(&legend, x + 290, y, &vol, LEGEND_PX, HPos::Right)?;
            y += 21;
        }
        if map.blocks.len() > shown {
            let more = format!("… {} more blocks", map.blocks.len() - shown);
            legend_text(&legend, x + 22, y, &more, LEGEND_PX)?;
            y += 21;
        }
        y += 14;
        let c0 = palette(0);
        for (mark, label) in [
            (Mark::Dot(c0, 4), "training camera"),
            (Mark::Ring(c0), "test camera"),
            (Mark::Line(INK), "viewing direction"),
            (Mark::Outline(c0), "sub-NeRF block box"),
            (Mark::Dot(c0, 1), "sample point"),
        ] {
            draw_entry(&legend, x, y, &mark, label)?;
            y += 25;
        }
        y += 6;
        legend_text(&legend, x, y, "colour = block", 14)?;
        Ok(())
    })
}

/// A legend symbol.
enum Mark {
    /// A short line.
    Line(RGBColor),
    /// A filled disc of the given radius.
    Dot(RGBColor, u32),
    /// A circle outline.
    Circle(RGBColor),
    /// A disc with a line through it (an estimate joined to its truth).
    DotLine(RGBColor),
    /// A disc inside a black ring.
    Ring(RGBColor),
    /// A rectangle outline.
    Outline(RGBColor),
    /// A filled square.
    Fill(RGBColor),
}

/// Width of a legend symbol plus the gap before its text, pixels.
const MARK_W: i32 = 34;

/// Draws one legend entry with its vertical centre at `y`; returns its width in pixels.
fn draw_entry(area: &Area<'_>, x: i32, y: i32, mark: &Mark, label: &str) -> Result<i32> {
    match *mark {
        Mark::Line(c) => area.draw(&PathElement::new(
            vec![(x, y), (x + 24, y)],
            c.stroke_width(3),
        ))?,
        Mark::Dot(c, r) => area.draw(&Circle::new((x + 12, y), r as i32, c.filled()))?,
        Mark::DotLine(c) => {
            area.draw(&PathElement::new(
                vec![(x, y + 5), (x + 24, y - 5)],
                c.stroke_width(1),
            ))?;
            area.draw(&Circle::new((x + 18, y - 3), 4, c.filled()))?;
        }
        Mark::Circle(c) => area.draw(&Circle::new((x + 12, y), 5, c.stroke_width(2)))?,
        Mark::Ring(c) => {
            area.draw(&Circle::new((x + 12, y), 6, INK.filled()))?;
            area.draw(&Circle::new((x + 12, y), 4, c.filled()))?;
        }
        Mark::Outline(c) => area.draw(&Rectangle::new(
            [(x + 2, y - 7), (x + 22, y + 7)],
            c.stroke_width(2),
        ))?,
        Mark::Fill(c) => area.draw(&Rectangle::new(
            [(x + 4, y - 7), (x + 20, y + 7)],
            c.filled(),
        ))?,
    }
    legend_text(area, x + MARK_W, y, label, LEGEND_PX)?;
    Ok(MARK_W + text_width(label, LEGEND_PX)? as i32)
}

/// Splits legend entries into rows no wider than `max_w` pixels.
fn legend_rows(entries: &[(Mark, String)], max_w: u32) -> Result<Vec<Vec<&(Mark, String)>>> {
    let mut rows: Vec<Vec<&(Mark, String)>> = Vec::new();
    let mut used = u32::MAX;
    for e in entries {
        let ew = MARK_W as u32 + text_width(&e.1, LEGEND_PX)? + 28;
        if used.saturating_add(ew) > max_w || rows.is_empty() {
            rows.push(Vec::new());
            used = 0;
        }
        used += ew;
        rows.last_mut().expect("a row was pushed").push(e);
    }
    Ok(rows)
}

/// Draws legend rows from (`x`, `y`), 24 pixels apart.
fn draw_legend_rows(area: &Area<'_>, x: i32, y: i32, rows: &[Vec<&(Mark, String)>]) -> Result<()> {
    for (r, row) in rows.iter().enumerate() {
        let mut cx = x;
        for (mark, label) in row {
            cx += draw_entry(area, cx, y + 12 + 24 * r as i32, mark, label)? + 28;
        }
    }
    Ok(())
}

/// Left-aligned text with its vertical centre at `y`.
fn legend_text(area: &Area<'_>, x: i32, y: i32, s: &str, px: u32) -> Result<()> {
    legend_text_at(area, x, y, s, px, HPos::Left)
}

/// Text anchored horizontally by `hpos` at `x`, vertically centred at `y`.
fn legend_text_at(area: &Area<'_>, x: i32, y: i32, s: &str, px: u32, hpos: HPos) -> Result<()> {
    let style = text(px).pos(Pos::new(hpos, VPos::Center));
    area.draw(&Text::new(s.to_string(), (x, y), style))?;
    Ok(())
}

/// The chart text style of size `px`.
fn text(px: u32) -> TextStyle<'static> {
    (FONT, px).into_font().color(&INK)
}

/// Rendered width of `s` at size `px`.
fn text_width(s: &str, px: u32) -> Result<u32> {
    ensure_font()?;
    let (w, _) = (FONT, px)
        .into_font()
        .box_size(s)
        .map_err(|e| anyhow!("measuring text: {e:?}"))?;
    Ok(w)
}

/// `v` with up to three decimals and no trailing zeros.
fn trim_float(v: f64) -> String {
    let s = format!("{v:.3}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" {
        "0".to_string()
    } else {
        s.to_string()
    }
}

/// `v` to three significant digits (at most six decimals).
fn significant(v: f64) -> String {
    if v == 0.0 {
        return "0".to_string();
    }
    if !v.is_finite() {
        return format!("{v}");
    }
    let decimals = (2 - v.abs().log10().floor() as i32).clamp(0, 6) as usize;
    format!("{v:.decimals$}")
}

/// `v` in short scientific notation with superscript exponent, e.g. `3.4·10⁵`.
fn sci(v: f64) -> String {
    if !v.is_finite() {
        return "–".to_string();
    }
    if v.abs() < 1e4 {
        return format!("{v:.0}");
    }
    const SUP: [char; 10] = ['⁰', '¹', '²', '³', '⁴', '⁵', '⁶', '⁷', '⁸', '⁹'];
    // Rust's `{:e}` rounds the mantissa and carries into the exponent (9.99e5 → 1.0e6).
    let s = format!("{v:.1e}");
    let (mantissa, exp) = s.split_once('e').unwrap_or((&s, "0"));
    let exp: String = exp
        .chars()
        .map(|c| c.to_digit(10).map_or('⁻', |d| SUP[d as usize]))
        .collect();
    format!("{mantissa}·10{exp}")
}

/// The bounding box of finite points, padded by 4 % and at least 1 m wide on each axis.
#[derive(Clone, Copy)]
struct Extent {
    min: [f64; 2],
    max: [f64; 2],
}

impl Extent {
    fn of<'a>(points: impl IntoIterator<Item = &'a [f64; 2]>) -> Extent {
        let mut min = [f64::INFINITY; 2];
        let mut max = [f64::NEG_INFINITY; 2];
        for p in points.into_iter().filter(|p| finite(**p)) {
            for k in 0..2 {
                min[k] = min[k].min(p[k]);
                max[k] = max[k].max(p[k]);
            }
        }
        if min[0] > max[0] {
            return Extent {
                min: [-1.0; 2],
                max: [1.0; 2],
            };
        }
        let span = (max[0] - min[0]).max(max[1] - min[1]).max(1.0);
        for k in 0..2 {
            let pad = 0.5 * (span * 0.04).max(1.0 - (max[k] - min[k])).max(0.0);
            min[k] -= pad;
            max[k] += pad;
        }
        Extent { min, max }
    }
}

type MapChart<'a, 'b> =
    ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// A map chart on `area` showing `extent` with the same metres per pixel on both axes, axes
/// labelled in metres.
fn equal_aspect_chart<'a, 'b>(area: &'a Area<'b>, extent: Extent) -> Result<MapChart<'a, 'b>> {
    let builder = || {
        let mut b = ChartBuilder::on(area);
        b.margin(12)
            .margin_right(24)
            .x_label_area_size(52)
            .y_label_area_size(80);
        b
    };
    let (pw, ph) = {
        let probe = builder().build_cartesian_2d(0.0..1.0, 0.0..1.0)?;
        probe.plotting_area().dim_in_pixel()
    };
    let (pw, ph) = (f64::from(pw.max(1)), f64::from(ph.max(1)));
    let ex = extent.max[0] - extent.min[0];
    let ey = extent.max[1] - extent.min[1];
    let scale = (ex / pw).max(ey / ph);
    let cx = 0.5 * (extent.min[0] + extent.max[0]);
    let cy = 0.5 * (extent.min[1] + extent.max[1]);
    let (hx, hy) = (0.5 * pw * scale, 0.5 * ph * scale);
    let mut chart = builder().build_cartesian_2d(cx - hx..cx + hx, cy - hy..cy + hy)?;
    chart
        .configure_mesh()
        .x_desc("x (m)")
        .y_desc("y (m)")
        .axis_desc_style(text(DESC_PX))
        .label_style(text(LABEL_PX))
        .x_label_formatter(&|v| trim_float(*v))
        .y_label_formatter(&|v| trim_float(*v))
        .bold_line_style(RGBColor(222, 222, 222))
        .light_line_style(RGBColor(242, 242, 242))
        .max_light_lines(1)
        .axis_style(INK)
        .draw()?;
    Ok(chart)
}

/// The world window of a map chart.
fn view_of(chart: &MapChart<'_, '_>) -> ([f64; 2], [f64; 2]) {
    let x = chart.x_range();
    let y = chart.y_range();
    ([x.start, y.start], [x.end, y.end])
}

/// Largest coordinate magnitude drawn on a map, metres; anything beyond is treated as invalid.
const MAX_COORD: f64 = 1e9;

/// Whether `p` is a drawable map position: finite and within [`MAX_COORD`].
fn finite(p: [f64; 2]) -> bool {
    p[0].abs() <= MAX_COORD && p[1].abs() <= MAX_COORD
}

fn inside(p: [f64; 2], min: [f64; 2], max: [f64; 2]) -> bool {
    finite(p) && (0..2).all(|k| p[k] >= min[k] && p[k] <= max[k])
}

fn clamp_to(p: [f64; 2], min: [f64; 2], max: [f64; 2]) -> [f64; 2] {
    [p[0].clamp(min[0], max[0]), p[1].clamp(min[1], max[1])]
}

/// The part of segment `a`–`b` inside the box `[min, max]` (Liang–Barsky), if any.
fn clip_segment(
    a: [f64; 2],
    b: [f64; 2],
    min: [f64; 2],
    max: [f64; 2],
) -> Option<([f64; 2], [f64; 2])> {
    if !(finite(a) && finite(b)) {
        return None;
    }
    let d = [b[0] - a[0], b[1] - a[1]];
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for k in 0..2 {
        for (p, q) in [(-d[k], a[k] - min[k]), (d[k], max[k] - a[k])] {
            if p == 0.0 {
                if q < 0.0 {
                    return None;
                }
            } else {
                let r = q / p;
                if p < 0.0 {
                    t0 = t0.max(r);
                } else {
                    t1 = t1.min(r);
                }
            }
        }
    }
    if t0 > t1 {
        return None;
    }
    let at = |t: f64| [a[0] + t * d[0], a[1] + t * d[1]];
    Some((at(t0), at(t1)))
}

/// Registers the embedded font once.
fn ensure_font() -> Result<()> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    if *REGISTERED.get_or_init(|| register_font(FONT, FontStyle::Normal, FONT_TTF).is_ok()) {
        Ok(())
    } else {
        bail!("the embedded chart font does not parse")
    }
}

/// Draws on a white `size` bitmap with `draw` and writes it to `path` as a PNG, atomically.
fn render(
    path: &Path,
    (w, h): (u32, u32),
    draw: impl FnOnce(&Area<'_>) -> Result<()>,
) -> Result<()> {
    ensure_font()?;
    if !(16..=8192).contains(&w) || !(16..=8192).contains(&h) {
        bail!("chart size {w}×{h} is out of range");
    }
    let mut pixels = vec![255u8; w as usize * h as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, (w, h)).into_drawing_area();
        draw(&root).with_context(|| format!("drawing {}", path.display()))?;
        root.present()?;
    }
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes)
        .write_image(&pixels, w, h, image::ExtendedColorType::Rgb8)
        .context("encoding PNG")?;
    matloc_core::fsutil::write_atomic(path, &bytes)
        .with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Decodes the PNG at `path` and checks its size and that it carries text and lines.
    fn check_png(path: &Path, size: (u32, u32)) {
        let img = image::open(path)
            .unwrap_or_else(|e| panic!("{} does not decode: {e}", path.display()))
            .to_rgb8();
        assert_eq!(img.dimensions(), size, "{}", path.display());
        let dark = img
            .pixels()
            .filter(|p| p.0.iter().all(|&c| c < 110))
            .count();
        assert!(dark > 800, "{}: only {dark} dark pixels", path.display());
    }

    fn coloured(img: &image::RgbImage, c: RGBColor) -> usize {
        img.pixels().filter(|p| p.0 == [c.0, c.1, c.2]).count()
    }

    #[test]
    fn charts_draw_readable_pngs() {
        let dir = tempfile::tempdir().unwrap();
        let t: Vec<f64> = (1..40)
            .map(|k| 0.01 * f64::from(k) * f64::from(k))
            .collect();
        let r: Vec<f64> = t.iter().map(|v| v * 2.0).collect();
        let series = [
            ErrorSeries {
                name: "matloc",
                translation_m: &t,
                rotation_deg: &r,
                queries: 45,
            },
            ErrorSeries {
                name: "inerf",
                translation_m: &r,
                rotation_deg: &t,
                queries: 39,
            },
        ];
        let cdf = dir.path().join("error_cdf.png");
        error_cdfs(&cdf, "error CDF", &series).unwrap();
        check_png(&cdf, (1400, 620));
        let img = image::open(&cdf).unwrap().to_rgb8();
        assert!(coloured(&img, palette(0)) > 300 && coloured(&img, palette(1)) > 300);

        let train: Vec<[f64; 2]> = (0..50)
            .map(|k| [f64::from(k) * 4.0, f64::from(k % 7) * 9.0])
            .collect();
        let truth = [[10.0, 10.0], [100.0, 40.0]];
        let pairs = [([10.0, 10.0], [12.0, 9.0]), ([100.0, 40.0], [1e4, 40.0])];
        let boxes = [MapBox {
            min: [0.0, 0.0],
            max: [120.0, 60.0],
            color: 6,
            label: "block 0".into(),
        }];
        let estimates = [EstimateSeries {
            name: "matloc",
            pairs: &pairs,
        }];
        let map = TopDown {
            title: "top-down",
            train_cameras: &train,
            boxes: &boxes,
            boxes_legend: "block bounds",
            truth: &truth,
            estimates: &estimates,
        };
        let top = dir.path().join("topdown.png");
        topdown(&top, &map).unwrap();
        check_png(&top, (1200, 900));

        let parts = [("render".to_string(), 0.5), ("match".to_string(), 0.25)];
        let bars = [
            StackedBar {
                label: "matloc",
                parts: &parts,
            },
            StackedBar {
                label: "inerf",
                parts: &parts[..1],
            },
        ];
        let st = dir.path().join("stage_times.png");
        stage_bars(&st, "stage times", "time (s)", "s", &bars).unwrap();
        check_png(&st, (BARS_W, bars_height(2, 1)));

        let points: Vec<([f64; 2], usize)> = (0..5000)
            .map(|k| ([f64::from(k % 100), f64::from(k / 100)], k as usize % 2))
            .collect();
        let blocks = [
            PartitionBlock {
                id: 0,
                min: [0.0, 0.0],
                max: [60.0, 50.0],
                poses: 12,
                volume_m3: 3.5e5,
            },
            PartitionBlock {
                id: 1,
                min: [40.0, 0.0],
                max: [100.0, 50.0],
                poses: 9,
                volume_m3: 3.1e5,
            },
        ];
        let cameras = [
            CameraMark {
                position: [10.0, 10.0],
                direction: [1.0, 0.0],
                block: Some(0),
                test: false,
            },
            CameraMark {
                position: [90.0, 40.0],
                direction: [0.0, -1.0],
                block: None,
                test: true,
            },
        ];
        let pm = PartitionMap {
            title: "partition",
            scene_min: [0.0, 0.0],
            scene_max: [100.0, 50.0],
            points: &points,
            blocks: &blocks,
            cameras: &cameras,
        };
        let part = dir.path().join("partition.png");
        partition_map(&part, &pm).unwrap();
        check_png(&part, (1250, 900));
        // Atomic writes leave no temporary file behind.
        let names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names.len(), 4, "{names:?}");
    }

    #[test]
    fn degenerate_data_draws_without_panicking() {
        let dir = tempfile::tempdir().unwrap();
        let odd = [f64::NAN, f64::INFINITY, -1.0, 0.0, 1e300];
        let one = [0.5];
        let series = [
            ErrorSeries {
                name: "none",
                translation_m: &[],
                rotation_deg: &[],
                queries: 0,
            },
            ErrorSeries {
                name: "odd",
                translation_m: &odd,
                rotation_deg: &odd,
                queries: 2,
            },
            ErrorSeries {
                name: "one",
                translation_m: &one,
                rotation_deg: &one,
                queries: 1,
            },
        ];
        for (k, s) in [&series[..0], &series[..]].into_iter().enumerate() {
            let p = dir.path().join(format!("cdf{k}.png"));
            error_cdfs(&p, "", s).unwrap();
            check_png(&p, (1400, 620));
        }

        let nan = [f64::NAN, 1.0];
        let pairs = [
            (nan.map(|v| v), [0.0, 0.0]),
            ([0.0, 0.0], [f64::INFINITY, 0.0]),
            ([1.0, 1.0], [1.0, 1.0]),
        ];
        let boxes = [MapBox {
            min: [f64::NAN, 0.0],
            max: [1.0, 1.0],
            color: 0,
            label: String::new(),
        }];
        let estimates = [EstimateSeries {
            name: "x",
            pairs: &pairs,
        }];
        for (k, (train, truth)) in [
            (&[][..], &[][..]),
            (&[[5.0, 5.0]][..], &[nan.map(|v| v * 2.0)][..]),
        ]
        .into_iter()
        .enumerate()
        {
            let map = TopDown {
                title: "",
                train_cameras: train,
                boxes: if k == 0 { &[] } else { &boxes },
                boxes_legend: "",
                truth,
                estimates: if k == 0 { &[] } else { &estimates },
            };
            let p = dir.path().join(format!("top{k}.png"));
            topdown(&p, &map).unwrap();
            check_png(&p, (1200, 900));
        }

        let parts = [
            ("a".to_string(), f64::NAN),
            ("b".to_string(), -3.0),
            ("c".to_string(), 0.0),
        ];
        let none: [(String, f64); 0] = [];
        for (k, bars) in [
            vec![],
            vec![
                StackedBar {
                    label: "x",
                    parts: &parts,
                },
                StackedBar {
                    label: "",
                    parts: &none,
                },
            ],
        ]
        .into_iter()
        .enumerate()
        {
            let p = dir.path().join(format!("bars{k}.png"));
            stage_bars(&p, "", "", "s", &bars).unwrap();
            let rows = if bars.is_empty() { 0 } else { 1 };
            check_png(&p, (BARS_W, bars_height(bars.len(), rows)));
        }

        let blocks = [PartitionBlock {
            id: 3,
            min: [0.0, 0.0],
            max: [f64::NAN, 1.0],
            poses: 0,
            volume_m3: f64::NAN,
        }];
        let cameras = [CameraMark {
            position: [f64::NAN, 0.0],
            direction: [f64::NAN, 1.0],
            block: Some(3),
            test: true,
        }];
        let points = [([f64::INFINITY, 0.0], 0), ([0.0, 0.0], 7)];
        for (k, (min, max)) in [
            ([0.0, 0.0], [0.0, 0.0]),
            ([f64::NAN; 2], [f64::INFINITY; 2]),
        ]
        .into_iter()
        .enumerate()
        {
            let pm = PartitionMap {
                title: "",
                scene_min: min,
                scene_max: max,
                points: if k == 0 { &[] } else { &points },
                blocks: if k == 0 { &[] } else { &blocks },
                cameras: if k == 0 { &[] } else { &cameras },
            };
            let p = dir.path().join(format!("part{k}.png"));
            partition_map(&p, &pm).unwrap();
            check_png(&p, (1250, 900));
        }
    }

    #[test]
    fn unwritable_path_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("missing").join("x.png");
        assert!(error_cdfs(&p, "", &[]).is_err());
        assert!(!p.exists());
    }

    #[test]
    fn volumes_use_short_scientific_notation() {
        assert_eq!(sci(999_997.0), "1.0·10⁶");
        assert_eq!(sci(3.4e5), "3.4·10⁵");
        assert_eq!(sci(812.4), "812");
        assert_eq!(sci(f64::NAN), "–");
    }

    #[test]
    fn segments_are_clipped_to_the_view() {
        let (min, max) = ([0.0, 0.0], [10.0, 10.0]);
        let (a, b) = clip_segment([5.0, 5.0], [25.0, 5.0], min, max).unwrap();
        assert_eq!((a, b), ([5.0, 5.0], [10.0, 5.0]));
        assert!(clip_segment([-5.0, -5.0], [-1.0, 20.0], min, max).is_none());
        assert!(clip_segment([f64::NAN, 0.0], [1.0, 1.0], min, max).is_none());
        let (a, b) = clip_segment([-10.0, 5.0], [20.0, 5.0], min, max).unwrap();
        assert_eq!((a, b), ([0.0, 5.0], [10.0, 5.0]));
    }
}
