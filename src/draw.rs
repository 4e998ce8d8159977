//! The structure as a picture (issue 25): members, joints, supports, channels and the
//! bolted connections of a plane or space frame model file, in an SVG. A plane frame is
//! drawn in its plane; a space frame in isometric projection (y up; screen right along
//! `(1, 0, −1)/√2`, screen up along `(−1, 2, −1)/√6`: the view from `(1, 1, 1)`).
//!
//! [`Geometry`] reads the places out of the file; [`Canvas`] projects them and draws, and
//! the commands add their own marks: `report` colours each connection by its parameter's
//! change from baseline ([`change_color`]), `diagnose` draws the shape residual per channel
//! and the located discrepancy.

use std::collections::HashMap;
use std::fmt::Write as _;

use crate::core::model::spec::{ModelSpec, SpaceFrameSpec};

type P3 = [f64; 3];

/// A connection as drawn: a point on its member near the joint, and the names of the
/// model's connections it stands for (one per sprung axis in a space frame).
#[derive(Debug, Clone)]
pub struct ConnectionMark {
    pub name: String,
    pub at: P3,
    pub model_names: Vec<String>,
}

/// The places of a frame model file.
#[derive(Debug, Clone, Default)]
pub struct Geometry {
    pub members: Vec<(String, P3, P3)>,
    pub joints: Vec<P3>,
    pub supports: Vec<P3>,
    pub connections: Vec<ConnectionMark>,
    /// Channel name → its location.
    pub channels: Vec<(String, P3)>,
    /// Nodes and mesh nodes `<member>.<k>` by name.
    locations: HashMap<String, P3>,
    planar: bool,
}

fn lerp(a: P3, b: P3, t: f64) -> P3 {
    std::array::from_fn(|i| a[i] + t * (b[i] - a[i]))
}

/// What a frame model file names, before the places are looked up.
struct Named {
    /// (name, from, to, elements) of each member.
    members: Vec<(String, String, String, usize)>,
    /// (name, member, node, model connection names) of each connection.
    conns: Vec<(String, String, String, Vec<String>)>,
    supports: Vec<String>,
    joints: Vec<String>,
    /// (name, location) of each channel.
    channels: Vec<(String, String)>,
}

impl Named {
    /// The names of a space frame, its node positions into `locations`.
    fn space(sf: &SpaceFrameSpec, locations: &mut HashMap<String, P3>) -> Self {
        for n in &sf.nodes {
            locations.insert(n.name.clone(), [n.x, n.y, n.z]);
        }
        Named {
            members: sf
                .members
                .iter()
                .map(|m| (m.name.clone(), m.from.clone(), m.to.clone(), m.elements))
                .collect(),
            conns: sf
                .connections
                .iter()
                .map(|c| {
                    (
                        c.name(),
                        c.member.clone(),
                        c.node.clone(),
                        c.axes().map(|(n, _)| n).collect(),
                    )
                })
                .collect(),
            supports: sf.supports.iter().map(|s| s.node.clone()).collect(),
            joints: sf.joints.iter().map(|j| j.node.clone()).collect(),
            channels: sf
                .channels
                .iter()
                .map(|c| (c.name.clone(), c.at.clone()))
                .collect(),
        }
    }

    /// The names of a plane frame, its node positions (z = 0) into `locations`.
    fn plane(spec: &ModelSpec, locations: &mut HashMap<String, P3>) -> Self {
        for n in &spec.nodes {
            locations.insert(n.name.clone(), [n.x, n.y, 0.0]);
        }
        Named {
            members: spec
                .members
                .iter()
                .map(|m| (m.name.clone(), m.from.clone(), m.to.clone(), m.elements))
                .collect(),
            conns: spec
                .connections
                .iter()
                .map(|c| {
                    let name = c
                        .name
                        .clone()
                        .unwrap_or_else(|| format!("{}@{}", c.member, c.node));
                    (name.clone(), c.member.clone(), c.node.clone(), vec![name])
                })
                .collect(),
            supports: spec.supports.iter().map(|s| s.node.clone()).collect(),
            joints: spec.joints.iter().map(|j| j.node.clone()).collect(),
            channels: spec
                .channels
                .iter()
                .map(|c| (c.name.clone(), c.at.clone()))
                .collect(),
        }
    }
}

impl Geometry {
    /// The geometry of a plane frame or a space frame; `None` for the generated solid.
    pub fn of(spec: &ModelSpec) -> Option<Self> {
        let mut g = Geometry::default();
        let named = if let Some(sf) = &spec.space_frame {
            Named::space(sf, &mut g.locations)
        } else if spec.solid_frame.is_none() {
            g.planar = true;
            Named::plane(spec, &mut g.locations)
        } else {
            return None;
        };
        let ends = g.place_members(&named.members);
        g.place_connections(named.conns, &ends);
        g.supports = named
            .supports
            .iter()
            .filter_map(|n| g.position(n))
            .collect();
        g.joints = named.joints.iter().filter_map(|n| g.position(n)).collect();
        g.channels = named
            .channels
            .into_iter()
            .filter_map(|(name, at)| Some((name, g.position(&at)?)))
            .collect();
        Some(g)
    }

    /// Each member whose ends are known, with its mesh nodes `<member>.<k>`; returns the
    /// end nodes (from, to) of each by name.
    fn place_members(
        &mut self,
        members: &[(String, String, String, usize)],
    ) -> HashMap<String, (String, String)> {
        let mut ends: HashMap<String, (String, String)> = HashMap::new();
        for (name, from, to, elements) in members {
            let (Some(&a), Some(&b)) = (self.locations.get(from), self.locations.get(to)) else {
                continue;
            };
            for k in 0..=*elements {
                self.locations.insert(
                    format!("{name}.{k}"),
                    lerp(a, b, k as f64 / *elements as f64),
                );
            }
            self.members.push((name.clone(), a, b));
            ends.insert(name.clone(), (from.clone(), to.clone()));
        }
        ends
    }

    /// Each connection whose member and node are known, marked on its member near the
    /// node (`ends`: each member's end nodes).
    fn place_connections(
        &mut self,
        conns: Vec<(String, String, String, Vec<String>)>,
        ends: &HashMap<String, (String, String)>,
    ) {
        for (name, member, node, model_names) in conns {
            let (Some((from, to)), Some(&at)) = (ends.get(&member), self.locations.get(&node))
            else {
                continue;
            };
            let other = if *from == node { to } else { from };
            if let Some(&far) = self.locations.get(other) {
                self.connections.push(ConnectionMark {
                    name,
                    at: lerp(at, far, 0.12),
                    model_names,
                });
            }
        }
    }

    /// The position of a node or mesh node `<member>.<k>`, or of a diagnosis location
    /// (`<node>.<dof>`, `<member>.<axis>`, `<member>.<k>.<axis>`: the part before the last
    /// dot), or the middle of a member.
    pub fn position(&self, at: &str) -> Option<P3> {
        if let Some(p) = self.locations.get(at) {
            return Some(*p);
        }
        if let Some(m) = self.members.iter().find(|m| m.0 == at) {
            return Some(lerp(m.1, m.2, 0.5));
        }
        let (head, _) = at.rsplit_once('.')?;
        self.position(head)
    }
}

/// A colour for a relative change from baseline: grey at 0, towards red for a loss and
/// blue for a gain, saturated at ±`full`.
pub fn change_color(change: f64, full: f64) -> String {
    let t = (change / full).clamp(-1.0, 1.0);
    let grey = [150.0, 150.0, 150.0];
    let end = if t < 0.0 {
        [192.0, 57.0, 43.0]
    } else {
        [36.0, 113.0, 163.0]
    };
    let a = t.abs();
    let c: Vec<u8> = (0..3)
        .map(|i| (grey[i] + a * (end[i] - grey[i])).round() as u8)
        .collect();
    format!("#{:02x}{:02x}{:02x}", c[0], c[1], c[2])
}

/// An SVG of a [`Geometry`] (module docs).
pub struct Canvas<'g> {
    g: &'g Geometry,
    svg: String,
    origin: (f64, f64),
    scale: f64,
    height: f64,
    pad: f64,
}

impl<'g> Canvas<'g> {
    /// A `width × height` picture with the frame drawn: members, joints (squares),
    /// supports (triangles), channels (dots), and a title.
    pub fn new(g: &'g Geometry, width: f64, height: f64, title: &str) -> Self {
        let pad = 70.0;
        let (origin, scale) = fit(g, width, height, pad);
        let mut c = Canvas {
            g,
            svg: String::new(),
            origin,
            scale,
            height,
            pad,
        };
        c.header(width, title);
        c.frame();
        c.channel_dots();
        c
    }

    /// The SVG's opening tag, white background and title (and the axes of a space frame).
    fn header(&mut self, width: f64, title: &str) {
        let height = self.height;
        let _ = writeln!(
            self.svg,
            r#"<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-family="sans-serif" font-size="12">"#
        );
        let _ = writeln!(
            self.svg,
            r#"<rect width="100%" height="100%" fill="white"/>"#
        );
        let _ = writeln!(
            self.svg,
            r#"<text x="10" y="20" font-size="14">{}</text>"#,
            escape(title)
        );
        if !self.g.planar {
            self.axes_key();
        }
    }

    /// Members (lines), supports (triangles) and joints (squares).
    fn frame(&mut self) {
        let g = self.g;
        for (name, a, b) in &g.members {
            let ((x1, y1), (x2, y2)) = (self.xy(*a), self.xy(*b));
            let _ = writeln!(
                self.svg,
                r##"<line x1="{x1:.1}" y1="{y1:.1}" x2="{x2:.1}" y2="{y2:.1}" stroke="#555" stroke-width="3" stroke-linecap="round"><title>{}</title></line>"##,
                escape(name)
            );
        }
        for p in &g.supports {
            let (x, y) = self.xy(*p);
            let _ = writeln!(
                self.svg,
                r##"<path d="M {x:.1} {y:.1} l -9 14 h 18 z" fill="#777"/>"##
            );
        }
        for p in &g.joints {
            let (x, y) = self.xy(*p);
            let _ = writeln!(
                self.svg,
                r##"<rect x="{:.1}" y="{:.1}" width="10" height="10" fill="#222"/>"##,
                x - 5.0,
                y - 5.0
            );
        }
    }

    /// The channels: one dot per place, its channels in the tooltip.
    fn channel_dots(&mut self) {
        let g = self.g;
        // One dot per place, its channels in the tooltip.
        let mut places: Vec<(P3, Vec<&str>)> = Vec::new();
        for (name, p) in &g.channels {
            match places.iter_mut().find(|(q, _)| q == p) {
                Some((_, names)) => names.push(name),
                None => places.push((*p, vec![name])),
            }
        }
        for (p, names) in places {
            let (x, y) = self.xy(p);
            let _ = writeln!(
                self.svg,
                r##"<circle cx="{x:.1}" cy="{y:.1}" r="3" fill="#1a5276"><title>{}</title></circle>"##,
                escape(&names.join(", "))
            );
        }
    }

    fn axes_key(&mut self) {
        // The global axes, bottom left.
        let (ox, oy) = (30.0, self.height - 30.0);
        for (axis, v) in [
            ("x", [1.0, 0.0, 0.0]),
            ("y", [0.0, 1.0, 0.0]),
            ("z", [0.0, 0.0, 1.0]),
        ] {
            let (dx, dy) = project(false, v);
            let (x, y) = (ox + 22.0 * dx, oy - 22.0 * dy);
            let _ = writeln!(
                self.svg,
                r##"<line x1="{ox}" y1="{oy}" x2="{x:.1}" y2="{y:.1}" stroke="#000"/><text x="{:.1}" y="{:.1}">{axis}</text>"##,
                x + 3.0 * dx.signum(),
                y - 3.0
            );
        }
    }

    /// Screen coordinates of a point.
    pub fn xy(&self, p: P3) -> (f64, f64) {
        let (u, v) = project(self.g.planar, p);
        (
            self.pad + (u - self.origin.0) * self.scale,
            self.height - self.pad - (v - self.origin.1) * self.scale,
        )
    }

    /// Each connection as a disc of radius 7, coloured by `color` (fill and a tooltip),
    /// or hollow when it gives none.
    pub fn connections(&mut self, color: impl Fn(&ConnectionMark) -> Option<(String, String)>) {
        for c in &self.g.connections {
            let (x, y) = self.xy(c.at);
            let (fill, note) = color(c).unwrap_or_else(|| ("none".into(), String::new()));
            let _ = writeln!(
                self.svg,
                r##"<circle cx="{x:.1}" cy="{y:.1}" r="7" fill="{fill}" stroke="#000" stroke-width="1"><title>{}{}</title></circle>"##,
                escape(&c.name),
                escape(&note)
            );
        }
    }

    /// A disc at `p` (shifted `dx` pixels right).
    pub fn disc(&mut self, p: P3, radius: f64, color: &str, dx: f64, title: &str) {
        let (x, y) = self.xy(p);
        let _ = writeln!(
            self.svg,
            r#"<circle cx="{:.1}" cy="{y:.1}" r="{radius:.1}" fill="{color}" fill-opacity="0.35"><title>{}</title></circle>"#,
            x + dx,
            escape(title)
        );
    }

    /// A cross at `p` with a label.
    pub fn cross(&mut self, p: P3, color: &str, label: &str) {
        let (x, y) = self.xy(p);
        let _ = writeln!(
            self.svg,
            r#"<path d="M {x:.1} {y:.1} l 10 -10 m -10 10 l -10 -10 m 10 10 l -10 10 m 10 -10 l 10 10" stroke="{color}" stroke-width="3"/><text x="{:.1}" y="{y:.1}" fill="{color}">{}</text>"#,
            x + 14.0,
            escape(label)
        );
    }

    /// A line of text at screen position (x, y).
    pub fn text(&mut self, x: f64, y: f64, text: &str) {
        let _ = writeln!(
            self.svg,
            r#"<text x="{x:.1}" y="{y:.1}">{}</text>"#,
            escape(text)
        );
    }

    /// A colour bar of [`change_color`] from −`full` to +`full` at the top right.
    pub fn change_legend(&mut self, width: f64, full: f64) {
        let (x0, y0) = (width - 230.0, 36.0);
        for k in 0..=20 {
            let t = -1.0 + k as f64 / 10.0;
            let _ = writeln!(
                self.svg,
                r#"<rect x="{:.1}" y="{y0}" width="9" height="12" fill="{}"/>"#,
                x0 + 9.0 * k as f64,
                change_color(t * full, full)
            );
        }
        let _ = writeln!(
            self.svg,
            r#"<text x="{x0}" y="{:.1}">−{:.0} %</text><text x="{:.1}" y="{:.1}" text-anchor="middle">0</text><text x="{:.1}" y="{:.1}" text-anchor="end">+{:.0} %</text>"#,
            y0 + 26.0,
            100.0 * full,
            x0 + 94.5,
            y0 + 26.0,
            x0 + 189.0,
            y0 + 26.0,
            100.0 * full
        );
    }

    pub fn finish(mut self) -> String {
        self.svg.push_str("</svg>\n");
        self.svg
    }
}

/// The frame with each connection coloured by its parameter's change from baseline in
/// estimate `e` (the drift filter's level when it has one); a connection the data do not
/// resolve on its own (alerts off) is drawn hollow. Shared by `report` and the console.
pub fn estimate_svg(
    g: &Geometry,
    model: &crate::core::model::Model,
    e: &crate::contract::Estimate,
    width: f64,
    height: f64,
) -> String {
    use crate::commands::diagnose::{largest_change, parameters_of};
    let title = format!(
        "{}: change of each connection from baseline, {}",
        e.structure,
        e.time.format("%Y-%m-%d %H:%M:%S UTC")
    );
    let mut c = Canvas::new(g, width, height, &title);
    c.change_legend(width, 0.5);
    c.connections(|mark| {
        let changes: Vec<(String, f64, String)> = parameters_of(model, &mark.model_names)
            .into_iter()
            .filter_map(|l| {
                let name = &model.parameters()[l].name;
                let p = e.parameters.iter().find(|p| p.name == *name)?;
                if p.alerts_off.is_some() {
                    return None;
                }
                let change = p.filtered.change.or(p.change)?;
                Some((name.clone(), change, format!(" (θ {:.3})", p.theta)))
            })
            .collect();
        largest_change(&changes)
    });
    c.text(
        10.0,
        38.0,
        "hollow: no estimate, or not resolved by the data on its own (alerts off)",
    );
    c.finish()
}

/// Screen-plane coordinates (module docs).
fn project(planar: bool, p: P3) -> (f64, f64) {
    if planar {
        (p[0], p[1])
    } else {
        (
            (p[0] - p[2]) / std::f64::consts::SQRT_2,
            (2.0 * p[1] - p[0] - p[2]) / 6f64.sqrt(),
        )
    }
}

/// The drawing's origin (its lower left corner in screen-plane coordinates) and scale
/// (pixels per unit of length): the members' projected extent fitted, centred, inside
/// `width × height` less `pad` on every side.
fn fit(g: &Geometry, width: f64, height: f64, pad: f64) -> ((f64, f64), f64) {
    let pts: Vec<(f64, f64)> = g
        .members
        .iter()
        .flat_map(|m| [m.1, m.2])
        .map(|p| project(g.planar, p))
        .collect();
    let (mut lo, mut hi) = (
        (f64::INFINITY, f64::INFINITY),
        (f64::NEG_INFINITY, f64::NEG_INFINITY),
    );
    for p in &pts {
        lo = (lo.0.min(p.0), lo.1.min(p.1));
        hi = (hi.0.max(p.0), hi.1.max(p.1));
    }
    if pts.is_empty() {
        (lo, hi) = ((0.0, 0.0), (1.0, 1.0));
    }
    let scale = ((width - 2.0 * pad) / (hi.0 - lo.0).max(1e-9))
        .min((height - 2.0 * pad) / (hi.1 - lo.1).max(1e-9));
    // Centre the drawing.
    let origin = (
        lo.0 - ((width - 2.0 * pad) / scale - (hi.0 - lo.0)) / 2.0,
        lo.1 - ((height - 2.0 * pad) / scale - (hi.1 - lo.1)) / 2.0,
    );
    (origin, scale)
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The isometric projection keeps lengths along the three axes equal (√(2/3) each) and
    /// sends the view direction (1, 1, 1) to a point.
    #[test]
    fn isometric_projection_is_isometric() {
        let len = |p: P3| {
            let (u, v) = project(false, p);
            u.hypot(v)
        };
        let e = (2.0f64 / 3.0).sqrt();
        for p in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]] {
            assert!((len(p) - e).abs() < 1e-15, "{p:?}");
        }
        assert!(len([1.0, 1.0, 1.0]) < 1e-15);
        // y is up.
        assert!(project(false, [0.0, 1.0, 0.0]).1 > 0.0);
    }

    #[test]
    fn change_colors_run_from_red_through_grey_to_blue() {
        assert_eq!(change_color(0.0, 0.5), "#969696");
        assert_eq!(change_color(-0.5, 0.5), "#c0392b");
        assert_eq!(change_color(-2.0, 0.5), "#c0392b");
        assert_eq!(change_color(0.5, 0.5), "#2471a3");
    }
}
