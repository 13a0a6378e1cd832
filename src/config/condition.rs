//! The small expression language of template `condition` fields (reference §2.5):
//! numbers, parameter names, `== != > < >= <=`, `&& ||`, `!`, parentheses and `isDefined(x)`.
//!
//! Evaluation follows wb-mqtt-serial's `EvalImpl` (`src/expression_evaluator.cpp`): a parameter
//! the config does not define is *undefined*, and an undefined operand makes a comparison false
//! (`!=` true) and makes `&&` and `||` false whatever the other operand, so `mode || x==1` is
//! false while `mode` is undefined. A condition that is undefined as a whole (a bare name) is
//! false. Comparisons, `isDefined`, `&&` and `||` are always defined; parentheses pass their
//! content's definedness through.
//!
//! Operator precedence is C's, as upstream: `< <= > >=` bind tighter than `== !=`, which bind
//! tighter than `&&`, then `||`; each level chains to the left (`a==1==1` is `(a==1)==1`).
//! Unary `!` is an extension of ours (wb-mqtt-serial refuses it); it keeps an undefined operand
//! undefined.

use std::collections::BTreeMap;

/// Why a condition could not be parsed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("condition `{text}`: {message} (at character {position})")]
pub struct ConditionError {
    pub text: String,
    pub message: String,
    pub position: usize,
}

/// A parsed condition.
#[derive(Debug, Clone, PartialEq)]
pub enum Condition {
    Number(f64),
    Parameter(String),
    IsDefined(String),
    Not(Box<Condition>),
    Compare(Box<Condition>, Comparison, Box<Condition>),
    And(Box<Condition>, Box<Condition>),
    Or(Box<Condition>, Box<Condition>),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Comparison {
    Eq,
    Ne,
    Lt,
    Le,
    Gt,
    Ge,
}

#[derive(Debug, Clone, PartialEq)]
enum Token {
    Number(f64),
    Name(String),
    Op(&'static str),
}

impl Condition {
    pub fn parse(text: &str) -> Result<Condition, ConditionError> {
        let tokens = tokenize(text)?;
        let mut parser = Parser {
            text,
            tokens,
            pos: 0,
            depth: 0,
        };
        if parser.tokens.len() > MAX_TOKENS {
            return Err(ConditionError {
                text: text.chars().take(40).collect::<String>() + "…",
                message: format!(
                    "the condition has {} parts; at most {MAX_TOKENS} are allowed",
                    parser.tokens.len()
                ),
                position: 1,
            });
        }
        let condition = parser.or()?;
        if parser.pos < parser.tokens.len() {
            return Err(parser.error("unexpected text after the end of the expression"));
        }
        Ok(condition)
    }

    /// True when the condition holds for these parameter values.
    pub fn holds(&self, params: &BTreeMap<String, f64>) -> bool {
        self.evaluate(params).is_some_and(|v| v != 0.0)
    }

    /// The value of the expression, None while it is undefined (a parameter the values do not
    /// have, or `!` of one).
    fn evaluate(&self, params: &BTreeMap<String, f64>) -> Option<f64> {
        let truth = |b: bool| Some(if b { 1.0 } else { 0.0 });
        match self {
            Condition::Number(v) => Some(*v),
            Condition::Parameter(name) => params.get(name).copied(),
            Condition::IsDefined(name) => truth(params.contains_key(name)),
            Condition::Not(inner) => inner.evaluate(params).map(|v| (v == 0.0) as u8 as f64),
            // Both operands are evaluated and both must be defined (no short cut), as upstream:
            // `1 || x` is false while `x` is undefined.
            Condition::And(a, b) => match (a.evaluate(params), b.evaluate(params)) {
                (Some(x), Some(y)) => truth(x != 0.0 && y != 0.0),
                _ => truth(false),
            },
            Condition::Or(a, b) => match (a.evaluate(params), b.evaluate(params)) {
                (Some(x), Some(y)) => truth(x != 0.0 || y != 0.0),
                _ => truth(false),
            },
            Condition::Compare(a, op, b) => match (a.evaluate(params), b.evaluate(params)) {
                (Some(x), Some(y)) => truth(match op {
                    Comparison::Eq => x == y,
                    Comparison::Ne => x != y,
                    Comparison::Lt => x < y,
                    Comparison::Le => x <= y,
                    Comparison::Gt => x > y,
                    Comparison::Ge => x >= y,
                }),
                _ => truth(*op == Comparison::Ne),
            },
        }
    }

    /// Parameter names the condition mentions (to check they exist in the template).
    pub fn parameters(&self) -> Vec<String> {
        let mut out = Vec::new();
        self.collect(&mut out);
        out
    }

    fn collect(&self, out: &mut Vec<String>) {
        match self {
            Condition::Parameter(name) | Condition::IsDefined(name) => out.push(name.clone()),
            Condition::Not(inner) => inner.collect(out),
            Condition::Compare(a, _, b) | Condition::And(a, b) | Condition::Or(a, b) => {
                a.collect(out);
                b.collect(out);
            }
            Condition::Number(_) => {}
        }
    }
}

const OPERATORS: [&str; 11] = ["==", "!=", ">=", "<=", "&&", "||", ">", "<", "(", ")", "!"];

fn tokenize(text: &str) -> Result<Vec<(Token, usize)>, ConditionError> {
    let chars: Vec<char> = text.chars().collect();
    let mut tokens = Vec::new();
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        if c.is_whitespace() {
            i += 1;
            continue;
        }
        if c.is_ascii_digit() || (c == '-' && chars.get(i + 1).is_some_and(|d| d.is_ascii_digit()))
        {
            let start = i;
            i += 1;
            while i < chars.len() && (chars[i].is_ascii_alphanumeric() || chars[i] == '.') {
                i += 1;
            }
            let literal: String = chars[start..i].iter().collect();
            let number = crate::config::values::parse_int_text(&literal)
                .map(|v| v as f64)
                .or_else(|| literal.parse::<f64>().ok())
                .ok_or_else(|| ConditionError {
                    text: text.to_string(),
                    message: format!("`{literal}` is not a number"),
                    position: start + 1,
                })?;
            tokens.push((Token::Number(number), start));
            continue;
        }
        if c.is_alphabetic() || c == '_' || c == '$' {
            let start = i;
            while i < chars.len()
                && (chars[i].is_alphanumeric() || chars[i] == '_' || chars[i] == '$')
            {
                i += 1;
            }
            tokens.push((Token::Name(chars[start..i].iter().collect()), start));
            continue;
        }
        let rest: String = chars[i..chars.len().min(i + 2)].iter().collect();
        match OPERATORS.iter().find(|op| rest.starts_with(**op)) {
            Some(op) => {
                tokens.push((Token::Op(op), i));
                i += op.chars().count();
            }
            None => {
                return Err(ConditionError {
                    text: text.to_string(),
                    message: format!("unexpected character `{c}`"),
                    position: i + 1,
                })
            }
        }
    }
    Ok(tokens)
}

/// Limits that keep parsing and evaluating on a small stack whatever a file holds (real
/// conditions have a few terms and one or two levels of parentheses).
const MAX_DEPTH: usize = 32;
const MAX_TOKENS: usize = 512;

struct Parser<'a> {
    text: &'a str,
    tokens: Vec<(Token, usize)>,
    pos: usize,
    /// Nesting of `(` and `!` at the current position.
    depth: usize,
}

impl Parser<'_> {
    fn error(&self, message: &str) -> ConditionError {
        let position = self
            .tokens
            .get(self.pos)
            .map(|(_, p)| p + 1)
            .unwrap_or(self.text.chars().count() + 1);
        ConditionError {
            text: self.text.to_string(),
            message: message.to_string(),
            position,
        }
    }

    fn peek_op(&self) -> Option<&'static str> {
        match self.tokens.get(self.pos) {
            Some((Token::Op(op), _)) => Some(op),
            _ => None,
        }
    }

    fn or(&mut self) -> Result<Condition, ConditionError> {
        let mut left = self.and()?;
        while self.peek_op() == Some("||") {
            self.pos += 1;
            left = Condition::Or(Box::new(left), Box::new(self.and()?));
        }
        Ok(left)
    }

    fn and(&mut self) -> Result<Condition, ConditionError> {
        let mut left = self.comparison()?;
        while self.peek_op() == Some("&&") {
            self.pos += 1;
            left = Condition::And(Box::new(left), Box::new(self.comparison()?));
        }
        Ok(left)
    }

    /// `== !=`, chained to the left over relational comparisons.
    fn comparison(&mut self) -> Result<Condition, ConditionError> {
        let mut left = self.relational()?;
        loop {
            let op = match self.peek_op() {
                Some("==") => Comparison::Eq,
                Some("!=") => Comparison::Ne,
                _ => return Ok(left),
            };
            self.pos += 1;
            let right = self.relational()?;
            left = Condition::Compare(Box::new(left), op, Box::new(right));
        }
    }

    /// `< <= > >=`, chained to the left.
    fn relational(&mut self) -> Result<Condition, ConditionError> {
        let mut left = self.primary()?;
        loop {
            let op = match self.peek_op() {
                Some("<") => Comparison::Lt,
                Some("<=") => Comparison::Le,
                Some(">") => Comparison::Gt,
                Some(">=") => Comparison::Ge,
                _ => return Ok(left),
            };
            self.pos += 1;
            let right = self.primary()?;
            left = Condition::Compare(Box::new(left), op, Box::new(right));
        }
    }

    fn primary(&mut self) -> Result<Condition, ConditionError> {
        if self.depth >= MAX_DEPTH {
            return Err(self.error(&format!(
                "parentheses or `!` nest more than {MAX_DEPTH} deep"
            )));
        }
        self.depth += 1;
        let result = self.primary_inner();
        self.depth -= 1;
        result
    }

    fn primary_inner(&mut self) -> Result<Condition, ConditionError> {
        let token = self.tokens.get(self.pos).map(|(t, _)| t.clone());
        match token {
            Some(Token::Number(v)) => {
                self.pos += 1;
                Ok(Condition::Number(v))
            }
            Some(Token::Name(name)) if name == "isDefined" => {
                self.pos += 1;
                self.expect("(")?;
                let inner = match self.tokens.get(self.pos) {
                    Some((Token::Name(param), _)) => param.clone(),
                    _ => return Err(self.error("isDefined needs a parameter name")),
                };
                self.pos += 1;
                self.expect(")")?;
                Ok(Condition::IsDefined(inner))
            }
            Some(Token::Name(name)) => {
                self.pos += 1;
                Ok(Condition::Parameter(name))
            }
            Some(Token::Op("!")) => {
                self.pos += 1;
                Ok(Condition::Not(Box::new(self.primary()?)))
            }
            Some(Token::Op("(")) => {
                self.pos += 1;
                let inner = self.or()?;
                self.expect(")")?;
                Ok(inner)
            }
            _ => Err(self.error("expected a number, a parameter name or `(`")),
        }
    }

    fn expect(&mut self, op: &str) -> Result<(), ConditionError> {
        if self.peek_op() == Some(op) {
            self.pos += 1;
            Ok(())
        } else {
            Err(self.error(&format!("expected `{op}`")))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn holds(text: &str, params: &[(&str, f64)]) -> bool {
        let params = params.iter().map(|(k, v)| (k.to_string(), *v)).collect();
        Condition::parse(text).unwrap().holds(&params)
    }

    #[test]
    fn comparisons_and_logic() {
        assert!(holds("in1_mode==3", &[("in1_mode", 3.0)]));
        assert!(!holds("in1_mode==3", &[("in1_mode", 2.0)]));
        assert!(holds(
            "a>1 && b<=2 || c",
            &[("a", 2.0), ("b", 2.0), ("c", 0.0)]
        ));
        assert!(holds("(a==1 || b==1) && c!=0", &[("b", 1.0), ("c", 5.0)]));
        assert!(holds("a >= -1", &[("a", -1.0)]));
        assert!(holds("x == 0x10", &[("x", 16.0)]));
        assert!(holds("!(a == 1)", &[("a", 2.0)]));
    }

    #[test]
    fn undefined_parameters() {
        assert!(!holds("Show_modes_as_range==1", &[]));
        assert!(holds("Show_modes_as_range!=1", &[]));
        assert!(!holds("a < 5", &[]));
        assert!(holds("isDefined(a)", &[("a", 0.0)]));
        assert!(!holds("isDefined(a)", &[]));
        assert!(holds("!isDefined(in1_mode) || in1_mode==3", &[]));
    }

    /// wb-mqtt-serial's `EvalImpl`: an undefined operand makes `&&`/`||` false whatever the
    /// other one; comparisons with it are false except `!=`; parentheses do not define it.
    #[test]
    fn undefined_operands_of_and_or() {
        let mode_given = [("mode", 0.0), ("x", 1.0)];
        let mode_missing = [("x", 1.0)];
        assert!(holds("mode||x==1", &mode_given));
        assert!(!holds("mode||x==1", &mode_missing));
        assert!(!holds("x==1||mode", &mode_missing));
        assert!(!holds("x==1||(mode)", &mode_missing));
        assert!(!holds("1||mode", &mode_missing));
        assert!(!holds("x&&mode", &mode_missing));
        assert!(!holds("mode", &mode_missing));
        assert!(!holds("(mode)", &mode_missing));
        // Comparisons, isDefined and the logical operators are always defined.
        assert!(holds("(mode==1)||x==1", &mode_missing));
        assert!(holds("mode!=1||x==0", &mode_missing));
        assert!(holds("isDefined(mode)==0||mode==3", &mode_missing));
        assert!(holds("(mode||x==1)==0", &mode_missing));
        assert!(holds("(mode&&x)!=1", &mode_missing));
        assert!(holds("mode>=0||x==1", &mode_missing));
        // `!` (ours) keeps an undefined operand undefined.
        assert!(!holds("!mode", &mode_missing));
        assert!(!holds("!mode||x==1", &mode_missing));
        assert!(holds("!mode||x==0", &mode_given));
    }

    /// Precedence as in C and wb-mqtt-serial's `GetPriority`; comparisons chain to the left.
    #[test]
    fn comparison_chains_and_precedence() {
        assert!(holds("a==1==1", &[("a", 1.0)]));
        assert!(holds("a==2==0", &[("a", 1.0)]));
        // `<` binds tighter than `==`: a == (b < 2).
        assert!(holds("a==b<2", &[("a", 1.0), ("b", 1.0)]));
        assert!(!holds("a==b<2", &[("a", 1.0), ("b", 3.0)]));
        assert!(holds("1<2<3", &[]));
        assert!(holds("3>2>0", &[]));
        assert!(!holds("3>2>1", &[]));
    }

    #[test]
    fn deep_nesting_is_an_error_not_a_crash() {
        let deep = format!("{}a==1{}", "(".repeat(20_000), ")".repeat(20_000));
        let err = Condition::parse(&deep).unwrap_err().to_string();
        assert!(err.contains("at most 512"), "{err}");
        let nested = format!("{}a==1{}", "(".repeat(40), ")".repeat(40));
        let err = Condition::parse(&nested).unwrap_err().to_string();
        assert!(err.contains("nest more than 32"), "{err}");
        let nots = format!("{}a", "!".repeat(100));
        assert!(Condition::parse(&nots).is_err());
        assert!(Condition::parse(&format!("{}a==1{}", "(".repeat(10), ")".repeat(10))).is_ok());
    }

    #[test]
    fn errors_say_where() {
        let err = Condition::parse("a == ").unwrap_err();
        assert_eq!(err.position, 6);
        assert!(Condition::parse("a = 1").is_err());
        assert!(Condition::parse("(a == 1").is_err());
        assert!(Condition::parse("a == 1 b").is_err());
        assert!(Condition::parse("isDefined(1)").is_err());
        assert_eq!(
            Condition::parse("a==1 && isDefined(b)")
                .unwrap()
                .parameters(),
            vec!["a", "b"]
        );
    }
}
