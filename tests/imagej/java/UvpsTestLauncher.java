// Test launcher for ImageJ 1.x under Xvfb: installs a guard against modal dialogs, then calls
// ij.ImageJ.main(args) (e.g. "-ijpath /abs/home -batch macro.ijm ''").
//
// Under Xvfb nobody can close a modal dialog, so a dialog would hang the test forever. On every
// Dialog WINDOW_OPENED this launcher either
//   - (default) prints "UVPS-TEST: dialog opened" with the dialog's title and text (Labels,
//     TextAreas, TextFields, MultiLineLabels, Checkboxes, Choices, Buttons) to stderr and halts
//     the JVM with status 3 (DIALOG_STATUS); or
//   - with -Duvps.screenshot.dir=/abs/dir, waits uvps.screenshot.delay_ms (default 1000) for the
//     dialog to paint, saves it as <dir>/<title>.png (painted off screen with printAll), prints
//     "UVPS-SCREENSHOT: <png>" to stderr, then presses the button named by uvps.screenshot.button
//     (default "OK"; the dialog is disposed when no such button exists), so the macro continues.
// ImageJ's own uncaught-exception and IJ.error paths in batch mode end up in a dialog, so they are
// caught by the same guard.
import java.awt.AWTEvent;
import java.awt.Button;
import java.awt.Checkbox;
import java.awt.Choice;
import java.awt.Component;
import java.awt.Container;
import java.awt.Dialog;
import java.awt.Label;
import java.awt.TextComponent;
import java.awt.Toolkit;
import java.awt.Window;
import java.awt.event.AWTEventListener;
import java.awt.event.ActionEvent;
import java.awt.event.WindowEvent;
import java.awt.image.BufferedImage;
import java.io.File;
import java.lang.reflect.Field;
import java.util.ArrayList;
import java.util.List;
import javax.imageio.ImageIO;
import javax.swing.AbstractButton;
import javax.swing.JLabel;
import javax.swing.text.JTextComponent;

public class UvpsTestLauncher {

    /** JVM exit status when a modal dialog opens in guard mode. */
    public static final int DIALOG_STATUS = 3;

    public static void main(String[] args) throws Exception {
        final String shotDir = System.getProperty("uvps.screenshot.dir");
        Toolkit.getDefaultToolkit().addAWTEventListener(new AWTEventListener() {
            @Override
            public void eventDispatched(AWTEvent event) {
                if (event.getID() != WindowEvent.WINDOW_OPENED) {
                    return;
                }
                Window window = ((WindowEvent) event).getWindow();
                if (!(window instanceof Dialog)) {
                    return;
                }
                final Dialog dialog = (Dialog) window;
                if (shotDir != null) {
                    Thread t = new Thread(new Runnable() {
                        @Override
                        public void run() {
                            screenshotAndClose(dialog, new File(shotDir));
                        }
                    }, "uvps-screenshot");
                    t.setDaemon(true);
                    t.start();
                } else {
                    System.out.flush();
                    System.err.println("UVPS-TEST: dialog opened: title=\""
                            + dialog.getTitle() + "\"");
                    System.err.println(describe(dialog));
                    System.err.flush();
                    Runtime.getRuntime().halt(DIALOG_STATUS);
                }
            }
        }, AWTEvent.WINDOW_EVENT_MASK);
        ij.ImageJ.main(args);
    }

    /** The text shown by a dialog: one line per text-bearing component, depth first. */
    static String describe(Container root) {
        List<String> lines = new ArrayList<String>();
        collect(root, lines);
        StringBuilder sb = new StringBuilder();
        for (String line : lines) {
            sb.append("  ").append(line).append('\n');
        }
        return sb.toString();
    }

    private static void collect(Component c, List<String> lines) {
        String text = null;
        if (c instanceof Label) {
            text = "label: " + ((Label) c).getText();
        } else if (c instanceof TextComponent) {
            text = "text: " + ((TextComponent) c).getText();
        } else if (c instanceof Button) {
            text = "button: " + ((Button) c).getLabel();
        } else if (c instanceof JLabel) {
            text = "label: " + ((JLabel) c).getText();
        } else if (c instanceof JTextComponent) {
            text = "text: " + ((JTextComponent) c).getText();
        } else if (c instanceof AbstractButton) {
            text = "button: " + ((AbstractButton) c).getText();
        } else if (c instanceof Checkbox) {
            text = "checkbox: " + ((Checkbox) c).getLabel() + " = " + ((Checkbox) c).getState();
        } else if (c instanceof Choice) {
            text = "choice: " + ((Choice) c).getSelectedItem();
        } else {
            text = multiLineLabelText(c);
        }
        if (text != null) {
            lines.add(text);
        }
        if (c instanceof Container) {
            for (Component child : ((Container) c).getComponents()) {
                collect(child, lines);
            }
        }
    }

    /**
     * ij.gui.MultiLineLabel (IJ.error, showMessage, waitForUser, macro errors) is a Canvas that
     * keeps its text in a package-private String[] "lines" and has no getter in 1.53t.
     */
    private static String multiLineLabelText(Component c) {
        try {
            Field f = c.getClass().getDeclaredField("lines");
            f.setAccessible(true);
            Object value = f.get(c);
            if (value instanceof String[]) {
                return "text: " + String.join("\n        ", (String[]) value);
            }
        } catch (Exception ignored) {
            // not a MultiLineLabel
        }
        return null;
    }

    private static void screenshotAndClose(Dialog dialog, File dir) {
        try {
            Thread.sleep(Long.getLong("uvps.screenshot.delay_ms", 1000L));
            dir.mkdirs();
            String name = dialog.getTitle() == null ? "dialog" : dialog.getTitle();
            name = name.replaceAll("[^A-Za-z0-9._-]+", "_");
            if (name.isEmpty()) {
                name = "dialog";
            }
            File png = new File(dir, name + ".png");
            for (int i = 2; png.exists(); i++) {
                png = new File(dir, name + "_" + i + ".png");
            }
            BufferedImage image = paint(dialog);
            ImageIO.write(image, "png", png);
            System.err.println("UVPS-SCREENSHOT: " + png.getAbsolutePath());
            System.err.flush();
        } catch (Exception e) {
            System.err.println("UVPS-SCREENSHOT: failed: " + e);
        }
        final String wanted = System.getProperty("uvps.screenshot.button", "OK");
        java.awt.EventQueue.invokeLater(new Runnable() {
            @Override
            public void run() {
                Button button = findButton(dialog, wanted);
                if (button != null) {
                    button.dispatchEvent(new ActionEvent(button, ActionEvent.ACTION_PERFORMED,
                            button.getActionCommand()));
                } else {
                    dialog.dispose();
                }
            }
        });
    }

    /**
     * Render the dialog off screen with printAll on the event thread. A java.awt.Robot screen
     * capture was tried first but is unreliable without a window manager: under load the dialog
     * reports bounds (0, 0) while X shows it elsewhere, which gives a black capture.
     */
    private static BufferedImage paint(final Dialog dialog) throws Exception {
        final BufferedImage[] out = new BufferedImage[1];
        java.awt.EventQueue.invokeAndWait(new Runnable() {
            @Override
            public void run() {
                dialog.validate();
                BufferedImage image = new BufferedImage(dialog.getWidth(), dialog.getHeight(),
                        BufferedImage.TYPE_INT_RGB);
                java.awt.Graphics2D g = image.createGraphics();
                g.setColor(dialog.getBackground() != null ? dialog.getBackground()
                        : java.awt.Color.LIGHT_GRAY);
                g.fillRect(0, 0, image.getWidth(), image.getHeight());
                dialog.printAll(g);
                g.dispose();
                out[0] = image;
            }
        });
        return out[0];
    }

    private static Button findButton(Container root, String label) {
        for (Component c : root.getComponents()) {
            if (c instanceof Button && label.equalsIgnoreCase(((Button) c).getLabel().trim())) {
                return (Button) c;
            }
            if (c instanceof Container) {
                Button b = findButton((Container) c, label);
                if (b != null) {
                    return b;
                }
            }
        }
        return null;
    }
}
