//! Uniform-grid broad phase: bodies bucketed by cell (counting sort, rebuilt each step, no
//! allocation once warm), so proximity queries cost grows with local density, not scene size.

use parry2d::math::Vec2;

pub struct Grid {
    cell: f32,
    origin: Vec2,
    columns: usize,
    rows: usize,
    /// `starts[c]..starts[c + 1]` indexes `items` for cell `c`.
    starts: Vec<u32>,
    items: Vec<u32>,
    cell_of: Vec<u32>,
    cursor: Vec<u32>,
}

impl Grid {
    /// A grid of `cell`-sized squares covering [−half_extent, half_extent]²; bodies outside
    /// are clamped into the border cells (queries stay correct, only slower there).
    pub fn new(half_extent: f32, cell: f32) -> Grid {
        let columns = ((2.0 * half_extent / cell).ceil() as usize).max(1);
        Grid {
            cell,
            origin: Vec2::splat(-half_extent),
            columns,
            rows: columns,
            starts: vec![0; columns * columns + 1],
            items: Vec::new(),
            cell_of: Vec::new(),
            cursor: Vec::new(),
        }
    }

    fn coords(&self, p: Vec2) -> (usize, usize) {
        let rel = (p - self.origin) / self.cell;
        let clamp = |v: f32, n: usize| (v.max(0.0) as usize).min(n - 1);
        (clamp(rel.x, self.columns), clamp(rel.y, self.rows))
    }

    pub fn rebuild(&mut self, positions: impl Iterator<Item = Vec2>) {
        self.cell_of.clear();
        for p in positions {
            let (cx, cy) = self.coords(p);
            self.cell_of.push((cy * self.columns + cx) as u32);
        }
        self.starts.fill(0);
        for &c in &self.cell_of {
            self.starts[c as usize + 1] += 1;
        }
        for i in 1..self.starts.len() {
            self.starts[i] += self.starts[i - 1];
        }
        self.items.resize(self.cell_of.len(), 0);
        self.cursor.clone_from(&self.starts);
        for (body, &c) in self.cell_of.iter().enumerate() {
            self.items[self.cursor[c as usize] as usize] = body as u32;
            self.cursor[c as usize] += 1;
        }
    }

    /// Calls `visit` for every body in a cell overlapping the square of half-size `radius`
    /// around `centre` (a superset of the bodies within `radius`).
    pub fn for_each_near(&self, centre: Vec2, radius: f32, mut visit: impl FnMut(usize)) {
        let (x0, y0) = self.coords(centre - Vec2::splat(radius));
        let (x1, y1) = self.coords(centre + Vec2::splat(radius));
        for cy in y0..=y1 {
            let row = cy * self.columns;
            let (a, b) = (
                self.starts[row + x0] as usize,
                self.starts[row + x1 + 1] as usize,
            );
            for &body in &self.items[a..b] {
                visit(body as usize);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn queries_find_exactly_the_bodies_a_brute_force_scan_finds() {
        let mut grid = Grid::new(50.0, 7.0);
        let points: Vec<Vec2> = (0..200)
            .map(|i| {
                let t = i as f32 * 0.7;
                Vec2::new((t * 1.3).sin() * 55.0, (t * 0.7).cos() * 48.0)
            })
            .collect();
        grid.rebuild(points.iter().copied());
        for (i, &centre) in points.iter().enumerate().step_by(7) {
            let mut found = Vec::new();
            grid.for_each_near(centre, 12.0, |j| {
                if (points[j] - centre).length() <= 12.0 {
                    found.push(j)
                }
            });
            found.sort();
            let expected: Vec<usize> = (0..points.len())
                .filter(|&j| (points[j] - centre).length() <= 12.0)
                .collect();
            assert_eq!(found, expected, "around body {i}");
        }
    }
}
