//! What stands on the table when an episode of a task starts: the cubes (colour, place, yaw),
//! which of them the task is about, and where it has to end (the bowl, the top of another
//! cube, the target marker), drawn from the episode's seed; the instructions each task gives (and,
//! where the instruction decides the goal, a wrong one naming another cube). Every object stands where the arm
//! reaches it with the gripper pointing down, and far enough from the others that the open jaw
//! closing on one cube does not sweep another.

use crate::goal::Goal;
use crate::shape::Rgb;
use crate::splitmix::SplitMix64;
use crate::task::{CUBE_HALF, Layout, MAX_CUBE_YAW, TASK, TaskKind, on_table};
use rapier3d::math::Vec3;
use std::f32::consts::FRAC_PI_2;

/// Smallest distance between two cubes' centres, metres: the open jaw reaches about 5.5 cm
/// beyond the centre of the cube it closes on, and a turned cube's corner 1.7 cm from its own.
const CUBES_APART: f32 = 0.09;
/// Smallest distance from a cube's centre to the bowl's, metres: 4.6 cm clear of the bowl's
/// wall (5.4 cm out), room for the fingers around the cube.
const CUBE_CLEAR_OF_BOWL: f32 = 0.1;
/// Range of the distance a cube is pushed, metres.
const PUSH_LENGTH: (f32, f32) = (0.06, 0.11);
/// How far behind the cube's centre the pushing finger comes down, metres: past a turned
/// cube's corner (1.7 cm) with some clearance. That point must be in reach too.
pub(crate) const PUSH_APPROACH: f32 = 0.025;
/// Range of distances from the pan axis the gripper reaches pointing down, from low over the
/// table to the height it carries a cube at, metres.
const REACH: (f32, f32) = (0.12, 0.235);
/// Range of azimuths from the arm's forward direction, either way, at which objects stand,
/// radians: in front of the arm in the top camera's view, and off the line straight ahead,
/// where the arm standing at home hides them from it.
const AZIMUTH: (f32, f32) = (0.2, 0.8);

/// The colour of a cube, as instructions name it and the cameras see it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum CubeColour {
    Red,
    Green,
    Yellow,
}

impl CubeColour {
    /// Every colour a cube comes in; apart from each other, from the bowl's blue, the arm's
    /// orange and the table's beige.
    pub const ALL: [CubeColour; 3] = [CubeColour::Red, CubeColour::Green, CubeColour::Yellow];

    /// The colour as instructions name it.
    pub fn name(self) -> &'static str {
        match self {
            CubeColour::Red => "red",
            CubeColour::Green => "green",
            CubeColour::Yellow => "yellow",
        }
    }

    /// The colour as drawn, RGB.
    pub fn rgb(self) -> Rgb {
        match self {
            CubeColour::Red => [0.85, 0.08, 0.08],
            CubeColour::Green => [0.1, 0.62, 0.2],
            CubeColour::Yellow => [0.95, 0.82, 0.1],
        }
    }
}

/// One cube as the episode starts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlacedCube {
    pub colour: CubeColour,
    /// Centre, metres (resting on the table).
    pub position: Vec3,
    /// Rotation about the vertical, radians.
    pub yaw: f32,
}

/// Everything on the table as an episode of `task` starts, and what the task asks.
#[derive(Clone, Debug, PartialEq)]
pub struct Arrangement {
    pub task: TaskKind,
    pub cubes: Vec<PlacedCube>,
    /// Index in `cubes` of the cube the task moves.
    pub subject: usize,
    /// Where that cube has to end.
    pub goal: Goal,
}

impl Arrangement {
    /// The arrangement of `task`'s episode of `seed`; for [`TaskKind::CubeInBowl`] the one of
    /// [`Layout::from_seed`].
    pub fn from_seed(task: TaskKind, seed: u64) -> Self {
        match task {
            TaskKind::CubeInBowl => Layout::from_seed(seed).into(),
            TaskKind::Stack => stack(seed),
            TaskKind::PushToTarget => push_to_target(seed),
            TaskKind::PickColour => pick_colour(seed),
        }
    }

    /// The cube the task moves, as it starts.
    pub fn subject(&self) -> &PlacedCube {
        &self.cubes[self.subject]
    }

    /// The language instruction (LeRobot `task`).
    pub fn instruction(&self) -> String {
        let colour = self.subject().colour.name();
        match (self.task, self.goal) {
            (TaskKind::CubeInBowl, _) => TASK.to_string(),
            (_, Goal::OnCube { base }) => {
                format!("put the {colour} cube on the {} cube", self.cubes[base].colour.name())
            }
            (_, Goal::OnTarget { .. }) => "push the cube onto the target".to_string(),
            (_, Goal::InBowl { .. }) => format!("put the {colour} cube in the bowl"),
        }
    }

    /// For a task whose instruction decides the goal ([`TaskKind::instruction_decides`]), the
    /// instruction naming another goal on the same table: the next cube's colour. Told it, a
    /// policy that reads the instruction goes for the wrong cube (and fails the episode's
    /// success test), while one that ignores language does what it does told the right one.
    pub fn wrong_instruction(&self) -> Option<String> {
        self.task.instruction_decides().then(|| self.naming((self.subject + 1) % self.cubes.len()))
    }

    /// This table with cube `subject` the one to move: where the instruction decides the goal, the
    /// same layout asking for another cube (a recording that shows every goal of a layout).
    pub fn with_subject(self, subject: usize) -> Self {
        assert!(subject < self.cubes.len(), "cube {subject} of {}", self.cubes.len());
        Arrangement { subject, ..self }
    }

    /// The instruction this arrangement would give if cube `subject` were the one to move.
    fn naming(&self, subject: usize) -> String {
        self.clone().with_subject(subject).instruction()
    }
}

impl TaskKind {
    /// The language instruction of this task's episode of `seed` (LeRobot `task`): for
    /// [`TaskKind::PickColour`] it names the colour the seed drew.
    pub fn instruction(self, seed: u64) -> String {
        Arrangement::from_seed(self, seed).instruction()
    }

    /// Whether the instruction alone says which of the objects on the table is the goal: only a
    /// policy that reads it can succeed.
    pub fn instruction_decides(self) -> bool {
        self == TaskKind::PickColour
    }

    /// Every instruction the task gives, over all seeds: one per cube it can name where the
    /// instruction decides, else its one instruction (the others' do not depend on the seed).
    pub fn instructions(self) -> Vec<String> {
        let arrangement = Arrangement::from_seed(self, 0);
        match self.instruction_decides() {
            true => (0..arrangement.cubes.len()).map(|subject| arrangement.naming(subject)).collect(),
            false => vec![arrangement.instruction()],
        }
    }

    /// The instruction told in place of `instruction` to check that a policy reads it: where it belongs to a task
    /// whose instruction decides the goal, the next goal's, as [`Arrangement::wrong_instruction`] names it on
    /// that instruction's tables; else `None`.
    pub fn another_goal(instruction: &str) -> Option<String> {
        let task = Self::of_instruction(instruction).filter(|task| task.instruction_decides())?;
        let all = task.instructions();
        let at = all.iter().position(|i| i == instruction)?;
        Some(all[(at + 1) % all.len()].clone())
    }

    /// The task that gives `instruction`, if the sim's tasks give it.
    pub fn of_instruction(instruction: &str) -> Option<TaskKind> {
        TaskKind::ALL.into_iter().find(|task| task.instructions().iter().any(|i| i == instruction))
    }
}

impl From<Layout> for Arrangement {
    fn from(layout: Layout) -> Self {
        Self {
            task: TaskKind::CubeInBowl,
            cubes: vec![PlacedCube { colour: CubeColour::Red, position: layout.cube_position, yaw: layout.cube_yaw }],
            subject: 0,
            goal: Goal::InBowl { bowl: layout.bowl_position },
        }
    }
}

/// The red cube on one side of the arm, the green one to stack it on on the other, as the
/// cube and the bowl of [`Layout`].
fn stack(seed: u64) -> Arrangement {
    let mut rng = SplitMix64(seed);
    let side = rng.side();
    let [red, green] = loop {
        let red = on_table(side * rng.range(0.2, 0.6), rng.range(0.15, 0.23), CUBE_HALF);
        let green = on_table(-side * rng.range(0.2, 0.6), rng.range(0.15, 0.22), CUBE_HALF);
        if apart(red, green) >= CUBES_APART {
            break [red, green];
        }
    };
    Arrangement {
        task: TaskKind::Stack,
        cubes: vec![place(CubeColour::Red, red, &mut rng), place(CubeColour::Green, green, &mut rng)],
        subject: 0,
        goal: Goal::OnCube { base: 1 },
    }
}

/// The red cube anywhere in reach and the target a push's length from it straight out from
/// one of its faces (a pushed cube goes where the face pushed on faces: each contact kicks it
/// along the contact's normal), with room behind the cube for the finger that pushes it.
fn push_to_target(seed: u64) -> Arrangement {
    let mut rng = SplitMix64(seed);
    loop {
        let position = on_table(rng.side() * rng.range(AZIMUTH.0, 0.6), rng.range(0.14, 0.22), CUBE_HALF);
        let yaw = rng.range(-MAX_CUBE_YAW, MAX_CUBE_YAW);
        let face = yaw + (rng.next_u64() % 4) as f32 * FRAC_PI_2;
        let heading = Vec3::new(face.cos(), face.sin(), 0.0);
        let target = (position + heading * rng.range(PUSH_LENGTH.0, PUSH_LENGTH.1)).with_z(0.0);
        if in_view(target) && reachable(target) && reachable(position - heading * PUSH_APPROACH) {
            return Arrangement {
                task: TaskKind::PushToTarget,
                cubes: vec![PlacedCube { colour: CubeColour::Red, position, yaw }],
                subject: 0,
                goal: Goal::OnTarget { target },
            };
        }
    }
}

/// The bowl on one side of the arm as in [`Layout`], a cube of every colour anywhere in reach
/// clear of the bowl and of each other, and the colour to put in the bowl.
fn pick_colour(seed: u64) -> Arrangement {
    let mut rng = SplitMix64(seed);
    let bowl = on_table(rng.side() * rng.range(0.35, 0.7), rng.range(0.16, 0.22), 0.0);
    let spots = loop {
        let spots = CubeColour::ALL
            .map(|_| on_table(rng.side() * rng.range(AZIMUTH.0, 0.75), rng.range(0.13, 0.23), CUBE_HALF));
        let clear_of_bowl = spots.iter().all(|spot| apart(*spot, bowl) >= CUBE_CLEAR_OF_BOWL);
        let clear_of_each_other =
            spots.iter().enumerate().all(|(i, a)| spots[i + 1..].iter().all(|b| apart(*a, *b) >= CUBES_APART));
        if clear_of_bowl && clear_of_each_other {
            break spots;
        }
    };
    let cubes = CubeColour::ALL.into_iter().zip(spots).map(|(colour, spot)| place(colour, spot, &mut rng)).collect();
    let subject = (rng.next_u64() % CubeColour::ALL.len() as u64) as usize;
    Arrangement { task: TaskKind::PickColour, cubes, subject, goal: Goal::InBowl { bowl } }
}

/// A cube of `colour` at `position`, turned by a yaw drawn from `rng`.
fn place(colour: CubeColour, position: Vec3, rng: &mut SplitMix64) -> PlacedCube {
    PlacedCube { colour, position, yaw: rng.range(-MAX_CUBE_YAW, MAX_CUBE_YAW) }
}

/// Horizontal distance between two points, metres.
fn apart(a: Vec3, b: Vec3) -> f32 {
    (a - b).truncate().length()
}

/// Whether the gripper reaches `point` on the table pointing down.
fn reachable(point: Vec3) -> bool {
    (REACH.0..REACH.1).contains(&apart(point, on_table(0.0, 0.0, 0.0)))
}

/// Whether `point` on the table is at an azimuth where objects stand (see [`AZIMUTH`]).
fn in_view(point: Vec3) -> bool {
    let from_pan_axis = point - on_table(0.0, 0.0, point.z);
    (AZIMUTH.0..=AZIMUTH.1).contains(&from_pan_axis.x.atan2(-from_pan_axis.y).abs())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::task::BOWL_INNER_RADIUS;

    const SEEDS: std::ops::Range<u64> = 0..200;

    #[test]
    fn the_first_task_is_the_layout_of_its_seed() {
        for seed in 0..20 {
            let layout = Layout::from_seed(seed);
            let arrangement = Arrangement::from_seed(TaskKind::CubeInBowl, seed);
            assert_eq!(arrangement.subject().position, layout.cube_position);
            assert_eq!(arrangement.subject().yaw, layout.cube_yaw);
            assert_eq!(arrangement.goal, Goal::InBowl { bowl: layout.bowl_position });
            assert_eq!(arrangement.cubes.len(), 1);
            assert_eq!(TaskKind::CubeInBowl.instruction(seed), TASK);
        }
    }

    #[test]
    fn arrangements_repeat_by_seed_and_differ_between_seeds() {
        for task in TaskKind::ALL {
            assert_eq!(Arrangement::from_seed(task, 3), Arrangement::from_seed(task, 3), "{task}");
            assert_ne!(Arrangement::from_seed(task, 3), Arrangement::from_seed(task, 4), "{task}");
        }
    }

    #[test]
    fn objects_stand_in_reach_apart_and_on_the_table() {
        for task in TaskKind::ALL {
            for seed in SEEDS {
                let arrangement = Arrangement::from_seed(task, seed);
                let cubes: Vec<Vec3> = arrangement.cubes.iter().map(|cube| cube.position).collect();
                for (i, cube) in arrangement.cubes.iter().enumerate() {
                    let spot = cube.position;
                    assert!(reachable(spot) && in_view(spot), "{task} seed {seed}: cube {i} at {spot:?}");
                    assert_eq!(cube.position.z, CUBE_HALF);
                    assert!(cube.yaw.abs() <= MAX_CUBE_YAW);
                    for other in &cubes[i + 1..] {
                        assert!(apart(cube.position, *other) >= CUBES_APART, "{task} seed {seed}: cubes too close");
                    }
                }
                match arrangement.goal {
                    Goal::InBowl { bowl } => {
                        assert!(reachable(bowl) && in_view(bowl), "{task} seed {seed}: bowl at {bowl:?}");
                        for cube in &cubes {
                            let clear = apart(*cube, bowl);
                            assert!(
                                clear > BOWL_INNER_RADIUS + 0.035,
                                "{task} seed {seed}: cube {clear} m from the bowl"
                            );
                        }
                    }
                    Goal::OnCube { base } => assert_ne!(base, arrangement.subject),
                    Goal::OnTarget { target } => {
                        assert!(reachable(target) && in_view(target), "{task} seed {seed}: target at {target:?}");
                        let cube = arrangement.subject();
                        let length = apart(target, cube.position);
                        assert!((PUSH_LENGTH.0..PUSH_LENGTH.1).contains(&length), "{task} seed {seed}: {length}");
                        let push = target - cube.position;
                        let off_face = (push.y.atan2(push.x) - cube.yaw).rem_euclid(FRAC_PI_2);
                        assert!(off_face.min(FRAC_PI_2 - off_face) < 1e-3, "{task} seed {seed}: not along a face");
                    }
                }
            }
        }
    }

    #[test]
    fn instructions_list_every_seed_s_and_name_their_task() {
        for task in TaskKind::ALL {
            let listed = task.instructions();
            for seed in SEEDS {
                let instruction = task.instruction(seed);
                assert!(listed.contains(&instruction), "{task} seed {seed}: {instruction:?} not in {listed:?}");
                assert_eq!(TaskKind::of_instruction(&instruction), Some(task));
            }
        }
        assert_eq!(TaskKind::PickColour.instructions().len(), CubeColour::ALL.len());
        assert_eq!(TaskKind::of_instruction("juggle the cubes"), None);
    }

    #[test]
    fn a_wrong_instruction_names_another_cube_only_where_the_instruction_decides() {
        for seed in SEEDS {
            let arrangement = Arrangement::from_seed(TaskKind::PickColour, seed);
            let wrong = arrangement.wrong_instruction().unwrap();
            assert_ne!(wrong, arrangement.instruction());
            assert!(TaskKind::PickColour.instructions().contains(&wrong));
            // The held-out evaluation, which has the instruction and not the table, tells the same other goal.
            assert_eq!(TaskKind::another_goal(&arrangement.instruction()), Some(wrong));
            for task in [TaskKind::CubeInBowl, TaskKind::Stack, TaskKind::PushToTarget] {
                let arrangement = Arrangement::from_seed(task, seed);
                assert_eq!(arrangement.wrong_instruction(), None);
                assert_eq!(TaskKind::another_goal(&arrangement.instruction()), None);
            }
        }
    }

    #[test]
    fn every_colour_is_asked_for_and_named_in_the_instruction() {
        let mut asked = Vec::new();
        for seed in SEEDS {
            let arrangement = Arrangement::from_seed(TaskKind::PickColour, seed);
            let colour = arrangement.subject().colour;
            assert_eq!(arrangement.instruction(), format!("put the {} cube in the bowl", colour.name()));
            assert_eq!(arrangement.cubes.len(), CubeColour::ALL.len());
            asked.push(colour);
        }
        for colour in CubeColour::ALL {
            let share = asked.iter().filter(|asked| **asked == colour).count();
            assert!(share > SEEDS.end as usize / 5, "{colour:?} asked {share} times");
        }
    }
}
