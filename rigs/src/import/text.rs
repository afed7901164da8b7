//! A whitespace tokenizer with line numbers, shared by the CSE169 and BVH parsers.

use std::str::FromStr;

use super::ImportError;

/// One token and the 1-based line it starts on.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Token<'a> {
    pub text: &'a str,
    pub line: usize,
}

/// Tokens of a text file, consumed front to back. Braces are tokens of their own even when
/// written against a word (`root{`).
#[derive(Debug)]
pub(crate) struct Tokens<'a> {
    file: &'a str,
    tokens: Vec<Token<'a>>,
    pos: usize,
}

impl<'a> Tokens<'a> {
    /// Splits on any whitespace; `\n`, `\r\n` and a lone `\r` each end a line.
    pub fn new(file: &'a str, text: &'a str) -> Self {
        let mut tokens = Vec::new();
        let bytes = text.as_bytes();
        let mut line = 1;
        let mut start: Option<usize> = None;
        let push = |tokens: &mut Vec<Token<'a>>, from: usize, to: usize, line: usize| {
            if let Some(word) = text.get(from..to) {
                tokens.push(Token { text: word, line });
            }
        };
        for (i, &b) in bytes.iter().enumerate() {
            let brace = b == b'{' || b == b'}';
            if b.is_ascii_whitespace() || brace {
                if let Some(s) = start.take() {
                    push(&mut tokens, s, i, line);
                }
                if brace {
                    push(&mut tokens, i, i + 1, line);
                }
                if b == b'\n' || (b == b'\r' && bytes.get(i + 1) != Some(&b'\n')) {
                    line += 1;
                }
            } else if start.is_none() {
                start = Some(i);
            }
        }
        if let Some(s) = start {
            push(&mut tokens, s, bytes.len(), line);
        }
        Self {
            file,
            tokens,
            pos: 0,
        }
    }

    pub fn file(&self) -> &str {
        self.file
    }

    /// Tokens not yet consumed.
    pub fn remaining(&self) -> usize {
        self.tokens.len() - self.pos
    }

    pub fn peek(&self) -> Option<Token<'a>> {
        self.tokens.get(self.pos).copied()
    }

    /// The line of the next token, or of the last one at the end.
    pub fn line(&self) -> usize {
        self.tokens
            .get(self.pos.min(self.tokens.len().saturating_sub(1)))
            .map_or(1, |t| t.line)
    }

    pub fn next_token(&mut self, expected: &str) -> Result<Token<'a>, ImportError> {
        let t = self.peek().ok_or_else(|| ImportError::Eof {
            file: self.file.to_owned(),
            expected: expected.to_owned(),
        })?;
        self.pos += 1;
        Ok(t)
    }

    pub fn syntax(&self, token: Token<'_>, expected: &str) -> ImportError {
        ImportError::Syntax {
            file: self.file.to_owned(),
            line: token.line,
            expected: expected.to_owned(),
            found: token.text.chars().take(40).collect(),
        }
    }

    pub fn invalid(&self, line: usize, message: impl Into<String>) -> ImportError {
        ImportError::Invalid {
            file: self.file.to_owned(),
            line,
            message: message.into(),
        }
    }

    /// Consumes `word` (ASCII case-insensitive) or fails.
    pub fn expect(&mut self, word: &str) -> Result<Token<'a>, ImportError> {
        let t = self.next_token(&format!("`{word}`"))?;
        if t.text.eq_ignore_ascii_case(word) {
            Ok(t)
        } else {
            Err(self.syntax(t, &format!("`{word}`")))
        }
    }

    /// Consumes one of `words` (ASCII case-insensitive) or fails.
    pub fn expect_one_of(&mut self, words: &[&str]) -> Result<Token<'a>, ImportError> {
        let what = words.join("` or `");
        let t = self.next_token(&format!("`{what}`"))?;
        if words.iter().any(|w| t.text.eq_ignore_ascii_case(w)) {
            Ok(t)
        } else {
            Err(self.syntax(t, &format!("`{what}`")))
        }
    }

    /// Consumes the next token if it is `word`.
    pub fn eat(&mut self, word: &str) -> bool {
        if self
            .peek()
            .is_some_and(|t| t.text.eq_ignore_ascii_case(word))
        {
            self.pos += 1;
            true
        } else {
            false
        }
    }

    /// A finite number.
    pub fn number<T: FromStr + Into<f64> + Copy>(&mut self, what: &str) -> Result<T, ImportError> {
        let t = self.next_token(what)?;
        match t.text.parse::<T>() {
            Ok(v) if v.into().is_finite() => Ok(v),
            _ => Err(self.syntax(t, what)),
        }
    }

    pub fn f32(&mut self, what: &str) -> Result<f32, ImportError> {
        self.number::<f32>(what)
    }

    pub fn vec3(&mut self, what: &str) -> Result<glam::Vec3, ImportError> {
        Ok(glam::Vec3::new(
            self.f32(what)?,
            self.f32(what)?,
            self.f32(what)?,
        ))
    }

    /// A non-negative integer.
    pub fn count(&mut self, what: &str) -> Result<(usize, usize), ImportError> {
        let t = self.next_token(what)?;
        t.text
            .parse::<usize>()
            .map(|n| (n, t.line))
            .map_err(|_| self.syntax(t, what))
    }

    /// Checks that `count` items of `tokens_each` tokens can still follow, so a huge count in
    /// a small file fails before anything is allocated for it.
    pub fn check_count(
        &self,
        what: &str,
        count: usize,
        tokens_each: usize,
        line: usize,
    ) -> Result<(), ImportError> {
        if count.saturating_mul(tokens_each) > self.remaining() {
            Err(ImportError::Count {
                file: self.file.to_owned(),
                line,
                what: what.to_owned(),
                count,
            })
        } else {
            Ok(())
        }
    }

    /// Skips a balanced `{ … }` block whose `{` is the next token.
    pub fn skip_block(&mut self) -> Result<(), ImportError> {
        self.expect("{")?;
        let mut depth = 1usize;
        while depth > 0 {
            let t = self.next_token("`}`")?;
            match t.text {
                "{" => depth += 1,
                "}" => depth -= 1,
                _ => {}
            }
        }
        Ok(())
    }
}
