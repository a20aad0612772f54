"""Drive a viser (1.1.x) web viewer's GUI panel from Selenium (headless Chromium).

Selectors rely on viser's DOM: each labelled input is rendered as
``<div class="mantine-Flex-root"><p><label for=UUID>LABEL</label></p><div>INPUT</div></div>``,
the control panel carries ``data-testid="floating-panel"``, the 3D view is the
``canvas[data-engine^="three.js"]`` (created with ``preserveDrawingBuffer: true``), and
notifications are Mantine ``.mantine-Notification-root`` elements.
"""

from __future__ import annotations

import base64
import shutil
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

from selenium import webdriver
from selenium.common.exceptions import StaleElementReferenceException, WebDriverException
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.webdriver.common.keys import Keys
from selenium.webdriver.remote.webdriver import WebDriver
from selenium.webdriver.remote.webelement import WebElement

if TYPE_CHECKING:
    import numpy as np

T = TypeVar("T")

TIMEOUT = 10.0
#: Debian's Chromium and its driver (`make test` installs both); None when missing.
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
PANEL = '[data-testid="floating-panel"]'
CANVAS = 'canvas[data-engine^="three.js"]'
ROW_XPATH = "./ancestor::div[contains(@class, 'mantine-Flex-root')][1]"  # from a <label>
CHROME_ARGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-dev-shm-usage",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
)


def _ready(result: object) -> bool:
    try:
        return bool(result)
    except ValueError:  # e.g. a numpy array: any non-None object counts as ready
        return result is not None


def wait_for(predicate: Callable[[], T], timeout: float = TIMEOUT, what: str = "condition",
             interval: float = 0.05) -> T:
    """Poll ``predicate`` until it returns a truthy value (or an array) and return it.

    Exceptions raised by the predicate (stale/missing elements...) count as "not yet".
    Raises AssertionError naming ``what`` (and the last exception) on timeout.
    """
    deadline = time.monotonic() + timeout
    last: Exception | None = None
    while True:
        try:
            result = predicate()
            if _ready(result):
                return result
        except Exception as exc:  # noqa: BLE001 - retried until timeout, then reported
            last = exc
        if time.monotonic() >= deadline:
            detail = f" (last error: {type(last).__name__}: {last})" if last else ""
            raise AssertionError(f"timed out after {timeout:.1f}s waiting for {what}{detail}")
        time.sleep(interval)


def _xpath_literal(text: str) -> str:
    """Quote ``text`` as an XPath 1.0 string literal."""
    if "'" not in text:
        return f"'{text}'"
    if '"' not in text:
        return f'"{text}"'
    return "concat(" + ", \"'\", ".join(f"'{part}'" for part in text.split("'")) + ")"


def _visible(driver: WebDriver, by: str, selector: str) -> list[WebElement]:
    return [el for el in driver.find_elements(by, selector) if el.is_displayed()]


def open_browser(url: str, width: int = 900, height: int = 700,
                 timeout: float = 60.0) -> WebDriver:
    """Start headless Chromium (software WebGL), load ``url`` and wait until viser is connected.

    The viewport (not the outer window) is resized to ``width`` x ``height``.
    """
    opts = webdriver.ChromeOptions()
    for arg in (*CHROME_ARGS, f"--window-size={width},{height}"):
        opts.add_argument(arg)
    assert CHROMIUM and CHROMEDRIVER, "no chromium / chromedriver on PATH"
    opts.binary_location = CHROMIUM
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    try:
        inner_w, inner_h = driver.execute_script("return [innerWidth, innerHeight];")
        if (inner_w, inner_h) != (width, height):
            outer = driver.get_window_size()
            driver.set_window_size(outer["width"] + width - inner_w,
                                   outer["height"] + height - inner_h)
        driver.get(url)
        wait_for(lambda: _visible(driver, By.CSS_SELECTOR, CANVAS), timeout, "the three.js canvas")
        wait_for(lambda: _visible(driver, By.CSS_SELECTOR, PANEL), timeout, "the viser GUI panel")
        wait_for(lambda: "Connected" in driver.find_element(By.CSS_SELECTOR, PANEL).text
                 or _visible(driver, By.XPATH, "//*[@data-testid='floating-panel']//label"),
                 timeout, "viser to show 'Connected' (or any GUI input)")
    except BaseException:
        driver.quit()
        raise
    return driver


def _row(driver: WebDriver, label: str) -> WebElement:
    """Row container (label + input) of the first visible GUI input labelled ``label``."""
    xpath = f"//label[normalize-space(.)={_xpath_literal(label)}]"
    labels = _visible(driver, By.XPATH, xpath)
    if not labels:
        raise LookupError(f"no visible <label> with text {label!r}")
    return labels[0].find_element(By.XPATH, ROW_XPATH)


def _input_in_row(driver: WebDriver, label: str, css: str, kind: str,
                  timeout: float) -> WebElement:
    """Wait for the visible ``css`` element in the row of the GUI input labelled ``label``."""
    def find() -> WebElement | None:
        found = [el for el in _row(driver, label).find_elements(By.CSS_SELECTOR, css)
                 if el.is_displayed()]
        return found[0] if found else None

    return wait_for(find, timeout, f"GUI input labelled {label!r} with a {kind} ({css})")


def _replace_text(el: WebElement, text: str, single_update: bool = False) -> None:
    """Replace the text of ``el``.

    Default: click, Ctrl+A and type ``text`` (real key events; viser sends every prefix).
    ``single_update``: set the value through React's native value setter and dispatch one
    ``input`` event, so viser sends exactly one update.
    """
    if single_update:
        el.parent.execute_script(
            "const el = arguments[0];"
            "const proto = Object.getPrototypeOf(el);"
            "Object.getOwnPropertyDescriptor(proto, 'value').set.call(el, arguments[1]);"
            "el.dispatchEvent(new Event('input', {bubbles: true}));", el, text)
        return
    el.click()
    el.send_keys(Keys.CONTROL, "a")
    el.send_keys(text if text else Keys.BACKSPACE)


def _num_str(value: float) -> str:
    if isinstance(value, int) or float(value).is_integer():
        return str(int(value))
    return f"{value:.10f}".rstrip("0").rstrip(".")


def set_slider(driver: WebDriver, label: str, value: float, single_update: bool = False,
               timeout: float = TIMEOUT) -> None:
    """Set a viser slider by typing ``value`` into the number box next to it.

    Each keystroke is sent to the server, so on_update may also fire for a prefix (0 for
    0.25 when the old value was 0.7); ``single_update=True`` avoids that (see _replace_text).
    Returns once the slider thumb shows ``value``. Out-of-range values raise AssertionError
    (viser would send them unclamped, then clamp on blur).
    """
    box = _input_in_row(driver, label, "input.mantine-NumberInput-input", "number box", timeout)
    thumb = _input_in_row(driver, label, "[role='slider']", "slider thumb", timeout)
    lo, hi = (float(thumb.get_attribute(a) or "nan") for a in ("aria-valuemin", "aria-valuemax"))
    if not lo <= value <= hi:
        raise AssertionError(f"slider {label!r}: {value} is outside its range [{lo}, {hi}]")
    _replace_text(box, _num_str(value), single_update)

    def thumb_at_value() -> bool:
        thumb = _row(driver, label).find_element(By.CSS_SELECTOR, "[role='slider']")
        return abs(float(thumb.get_attribute("aria-valuenow") or "nan") - value) < 1e-6

    wait_for(thumb_at_value, timeout, f"slider {label!r} to show {value}")


def type_text(driver: WebDriver, label: str, text: str, submit: bool = True,
              single_update: bool = False, timeout: float = TIMEOUT) -> None:
    """Replace the text of a viser text input by typing ``text``.

    viser sends every change (each keystroke) to the server; no blur or Enter is needed.
    ``submit`` presses Enter afterwards, which only matters inside a viser form (submits it).
    ``single_update``: see _replace_text.
    """
    box = _input_in_row(driver, label, "input, textarea", "text box", timeout)
    _replace_text(box, text, single_update)
    wait_for(lambda: box.get_attribute("value") == text, timeout,
             f"text input {label!r} to contain {text!r}")
    if submit:
        box.send_keys(Keys.ENTER)


def click_button(driver: WebDriver, label: str, timeout: float = TIMEOUT) -> None:
    """Click the (first) visible, enabled button whose text is ``label``."""
    xpath = f"//button[normalize-space(.)={_xpath_literal(label)}]"

    def click() -> bool:
        buttons = [b for b in _visible(driver, By.XPATH, xpath) if b.is_enabled()]
        if buttons:
            buttons[0].click()  # an intercepted click raises and is retried
        return bool(buttons)

    wait_for(click, timeout, f"a visible, enabled button {label!r} to click")


def set_checkbox(driver: WebDriver, label: str, checked: bool, timeout: float = TIMEOUT) -> None:
    """Click the checkbox labelled ``label`` if needed so that it is ``checked``."""
    box = _input_in_row(driver, label, "input[type='checkbox']", "checkbox", timeout)
    if box.is_selected() != checked:
        box.click()
    wait_for(lambda: box.is_selected() == checked, timeout,
             f"checkbox {label!r} to be {'checked' if checked else 'unchecked'}")


def select_dropdown(driver: WebDriver, label: str, option: str, timeout: float = TIMEOUT) -> None:
    """Open the viser dropdown labelled ``label`` and click the option ``option``."""
    box = _input_in_row(driver, label, "input[role='combobox']", "dropdown", timeout)
    if box.get_attribute("value") == option:
        return
    box.click()
    listbox_id = wait_for(lambda: box.get_attribute("aria-controls"), timeout,
                          f"dropdown {label!r} to open")
    opt_xpath = (f"//*[@id={_xpath_literal(listbox_id)}]"
                 f"//*[@role='option'][normalize-space(.)={_xpath_literal(option)}]")
    wait_for(lambda: _visible(driver, By.XPATH, opt_xpath), timeout,
             f"option {option!r} in dropdown {label!r}")[0].click()
    wait_for(lambda: box.get_attribute("value") == option, timeout,
             f"dropdown {label!r} to show {option!r}")


def panel_text(driver: WebDriver, timeout: float = TIMEOUT) -> str:
    """Visible text of the GUI control panel (title, labels, markdown, button texts)."""
    return wait_for(lambda: _visible(driver, By.CSS_SELECTOR, PANEL), timeout,
                    "the viser GUI panel")[0].text


def dismiss_notifications(driver: WebDriver, wait_for_title: str | None = None,
                          timeout: float = TIMEOUT) -> int:
    """Close all visible viser notifications; return how many were closed.

    If ``wait_for_title`` is given, first wait for a notification containing that text
    (e.g. "Software WebGL", which appears shortly after the canvas starts).
    """
    css = ".mantine-Notification-root"
    if wait_for_title is not None:
        title = wait_for_title
        wait_for(lambda: any(title in n.text for n in _visible(driver, By.CSS_SELECTOR, css)),
                 timeout, f"a notification containing {title!r}")
    closed: list[WebElement] = []
    for note in _visible(driver, By.CSS_SELECTOR, css):
        try:
            note.find_element(By.CSS_SELECTOR, ".mantine-Notification-closeButton").click()
            closed.append(note)
        except WebDriverException:
            pass  # already gone, or a notification without a close button

    def gone(el: WebElement) -> bool:
        try:
            return not el.is_displayed()
        except StaleElementReferenceException:
            return True

    wait_for(lambda: all(gone(n) for n in closed), timeout, "closed notifications to disappear")
    return len(closed)


def canvas_screenshot(driver: WebDriver, path: str, timeout: float = TIMEOUT) -> np.ndarray:
    """Save the 3D canvas pixels (no GUI panel or notifications) as PNG and return HxWx3 uint8.

    Reads the WebGL canvas via ``toDataURL`` (viser sets preserveDrawingBuffer), composited
    on white like the page background. Needs numpy and Pillow (imported lazily).
    """
    import io

    import numpy as np
    from PIL import Image

    canvas = wait_for(lambda: _visible(driver, By.CSS_SELECTOR, CANVAS), timeout,
                      "the three.js canvas")[0]
    url = driver.execute_script("return arguments[0].toDataURL('image/png');", canvas)
    if not url or not url.startswith("data:image/png;base64,"):
        raise AssertionError(f"canvas.toDataURL returned no PNG: {str(url)[:60]!r}")
    rgba = Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGBA")
    white = Image.new("RGBA", rgba.size, (255, 255, 255, 255))
    rgb = Image.alpha_composite(white, rgba).convert("RGB")
    rgb.save(path)
    return np.asarray(rgb)
